"""The generated reference pages of the docs site (docs/reference/) cannot drift from the code:
the committed pages equal what scripts/gen_docs.py produces now, and the CLI page lists every
subcommand and option that ``hil --help`` (and each ``hil COMMAND --help``) prints."""

from __future__ import annotations

import contextlib
import importlib.util
import io
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
REFERENCE = ROOT / "docs" / "reference"


def _gen_docs():
    spec = importlib.util.spec_from_file_location("gen_docs", ROOT / "scripts" / "gen_docs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


GEN = _gen_docs()


@pytest.mark.parametrize("name", sorted(GEN.PAGES))
def test_committed_page_is_what_the_generator_writes_now(name: str) -> None:
    path = REFERENCE / name
    assert path.exists(), f"{path} missing: run python scripts/gen_docs.py"
    assert path.read_text(encoding="utf-8") == GEN.PAGES[name](), (
        f"docs/reference/{name} is out of date: run python scripts/gen_docs.py and commit it"
    )


def _help(argv: list[str]) -> str:
    """What ``hil ARGV --help`` prints, from the CLI's own parser."""
    from rt_controller.cli import build_parser

    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        build_parser().parse_args([*argv, "--help"])
    return out.getvalue()


def _subcommands(help_text: str) -> list[str]:
    """The subcommand names of a help text (the lines indented by four under the metavar)."""
    return re.findall(r"^    ([a-z][\w-]*)(?:\s|$)", help_text, re.M)


def _options(help_text: str) -> set[str]:
    """Every option string of a help text's argument lines ("  -h, --help  ...")."""
    found = set()
    for line in help_text.splitlines():
        if re.match(r"^  -", line):
            head = re.split(r"\s{2,}", line.strip())[0]
            found |= set(re.findall(r"(?<![\w-])--?[A-Za-z][\w-]*", head))
    return found


def _sections(page: str) -> dict[str, str]:
    parts = re.split(r"^## (hil[^{\n]*?)\s*(?:\{[^}]*\})?\s*$", page, flags=re.M)
    return {parts[i].strip(): parts[i + 1] for i in range(1, len(parts), 2)}


def test_the_cli_page_lists_every_subcommand_and_option_hil_help_knows() -> None:
    sections = _sections((REFERENCE / "cli.md").read_text(encoding="utf-8"))
    todo, seen = [[]], []
    while todo:
        argv = todo.pop(0)
        text = _help(argv)
        name = " ".join(["hil", *argv])
        seen.append(name)
        assert name in sections, f"docs/reference/cli.md has no section for {name}"
        for option in _options(text):
            assert re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", sections[name]), (
                f"docs/reference/cli.md: {name} does not list {option}"
            )
        todo += [[*argv, sub] for sub in _subcommands(text)]
    assert len(seen) > 10 and "hil bench loop" in seen
    assert set(sections) == set(seen), "the CLI page has sections hil --help does not know"


def test_the_installed_hil_help_names_the_same_subcommands() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "rt_controller.cli", "--help"],
        capture_output=True,
        text=True,
        check=True,
        cwd=ROOT,
    )
    assert _subcommands(done.stdout) == _subcommands(_help([]))
    sections = _sections((REFERENCE / "cli.md").read_text(encoding="utf-8"))
    for sub in _subcommands(done.stdout):
        assert f"hil {sub}" in sections


def test_table_cells_show_code_and_roles_as_the_api_pages_do() -> None:
    """One rule for Sphinx roles in the tables and on the API pages (``~`` shows the last
    name); a literal keeps its ``~`` (a home-relative path)."""
    from docgen.griffe_roles import plain_roles
    from docgen.markdown import esc

    text = "see ``~/can.conf``, :func:`~a.b` and :class:`X` (a_b)"
    assert esc(text) == r"see `~/can.conf`, `b` and `X` (a\_b)"
    assert plain_roles(text) == "see ``~/can.conf``, `b` and `X` (a_b)"
