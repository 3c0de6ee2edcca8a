"""The commands the docs print around ``examples/`` keep working as printed: every
``examples/...`` path the docs and the examples' own comments name exists, the ``hil
simulate`` line of the run-the-rig tutorial runs on ``examples/rig.toml`` from the repository's
root (where the tutorial says to run it), and the configuration page's error example is the
line ``hil`` prints. The files themselves are held by ``tests/hal/test_config.py`` (rig.toml),
``tests/controller/test_sweep_spec.py`` (the studies) and the notebook's integration test."""

from __future__ import annotations

import re
import shlex

from rt_controller.cli import main
from tests.support import REPO

EXAMPLES = REPO / "examples"
DOCS = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md")), *EXAMPLES.glob("*.toml")]


def test_every_examples_path_the_docs_name_exists():
    named = {
        (doc.relative_to(REPO).as_posix(), m.group(0).rstrip("."))
        for doc in DOCS
        for m in re.finditer(r"(?<![\w/])examples/[\w.-]+", doc.read_text(encoding="utf-8"))
    }
    assert any(path == "examples/robustness.toml" for _, path in named)
    missing = sorted((doc, path) for doc, path in named if not (REPO / path).exists())
    assert not missing, missing


def test_the_tutorials_simulate_line_runs_on_the_example_config(monkeypatch, capsys):
    text = (REPO / "docs" / "tutorials" / "run-the-rig.md").read_text(encoding="utf-8")
    line = re.search(r"^hil (simulate --config examples/rig\.toml[^\n#]*)", text, flags=re.M)
    assert line, "the tutorial no longer runs the example config"
    monkeypatch.chdir(REPO)
    assert main(shlex.split(line.group(1))) == 0
    assert "f_final_norm" in capsys.readouterr().out


def test_the_configuration_pages_error_example_is_what_hil_prints(tmp_path, monkeypatch, capsys):
    text = (REPO / "docs" / "concepts" / "configuration.md").read_text(encoding="utf-8")
    quoted = re.search(r"```text\n(hil simulate: error: bad\.toml: gains\.alpha: [^\n]*)\n", text)
    assert quoted, "the page no longer quotes the error"
    (tmp_path / "bad.toml").write_text("[gains]\nalpha = [[0.05, 0.0], [0.0, -0.1]]\n")
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", "--config", "bad.toml"]) == 2
    assert capsys.readouterr().err.strip() == quoted.group(1)
