"""Generate the reference pages of the docs site from the code, so they cannot drift.

Writes ``docs/reference/{cli,config,dbc,zenoh,schemas,cia402-od}.md``:

- ``cli.md``: every ``hil`` subcommand and option, walked from ``rt_controller.cli.build_parser()``;
- ``config.md``: every configuration key with its default, range and meaning, from the
  dataclasses of the ``hal/config/`` package (attribute docstrings, else the comment of the key
  in ``examples/rig.toml``) and its range table ``hal.config.ranges.RANGES``;
- ``dbc.md``: every CAN message and signal of ``hal/hil.dbc``, read with cantools;
- ``zenoh.md``: the zenoh key expressions (``KEY_*`` of ``hal/zenoh_session.py``);
- ``schemas.md``: the JSON Schemas of the MCAP topics and live channels (``*_SCHEMA`` dicts and
  ``*schema*.json`` files of the packages);
- ``cia402-od.md``: the emulated CiA 402 drive's object dictionary, read from its EDS
  (``hal/cia402_drive.eds``, which this script also writes from ``hal/cia402_od.py``).

    python scripts/gen_docs.py           # (re)write the pages
    python scripts/gen_docs.py --check   # exit 1 naming every page that is not up to date

The page builders are in ``scripts/docgen/``, one module per page (or pair of pages). The pages
are committed (the site builds from a clean clone); ``scripts/test.sh`` runs
``--check`` before ``mkdocs build --strict`` and ``tests/controller/test_docs_reference.py``
compares them too.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
for _path in (ROOT, ROOT / "scripts"):  # the packages, and this script's page builders (docgen/)
    if str(_path) not in sys.path:
        sys.path.insert(0, str(_path))

from docgen.can_pages import cia402_od_page, dbc_page  # noqa: E402
from docgen.cli_page import cli_page  # noqa: E402
from docgen.config_page import config_page  # noqa: E402
from docgen.message_pages import schemas_page, zenoh_page  # noqa: E402

OUT = ROOT / "docs" / "reference"


PAGES: dict[str, Callable[[], str]] = {
    "cli.md": cli_page,
    "config.md": config_page,
    "dbc.md": dbc_page,
    "zenoh.md": zenoh_page,
    "schemas.md": schemas_page,
    "cia402-od.md": cia402_od_page,
}


def generate() -> dict[str, str]:
    """``{file name: text}`` of every generated page."""
    return {name: build() for name, build in PAGES.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="only compare; exit 1 if stale")
    ap.add_argument("--out", type=Path, default=OUT, help=f"output folder (default {OUT})")
    args = ap.parse_args(argv)
    from hal.cia402_od import EDS_PATH, eds_text

    stale = []

    def compare(path: Path, text: str) -> None:
        if path.exists() and path.read_text(encoding="utf-8") == text:
            return
        stale.append(path)
        if not args.check:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text, encoding="utf-8")

    compare(EDS_PATH, eds_text())  # first: cia402-od.md is read from the shipped EDS
    for name, text in generate().items():
        compare(args.out / name, text)
    if args.check and stale:
        names = ", ".join(p.relative_to(ROOT).as_posix() for p in stale)
        print(f"gen_docs: out of date: {names}; run: python scripts/gen_docs.py", file=sys.stderr)
        return 1
    for path in stale:
        print(f"wrote {path.relative_to(ROOT).as_posix()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
