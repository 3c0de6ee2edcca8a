"""docs/architecture.md as a map of the code a new maintainer can trust: every product module
can be found from it, and its "who may import whom" part draws the imports the code has."""

from __future__ import annotations

import re
import sys
from pathlib import PurePosixPath

from rt_controller.cli import COMMAND_MODULES
from tests.controller.test_layering import CLI_DISPATCH, FORBIDDEN, ROOT, imported_packages

DOC = ROOT / "docs" / "architecture.md"
PACKAGES = tuple(sorted(FORBIDDEN))
SUFFIXES = (".py", ".json", ".dbc", ".eds")
DIST_NAMES = {"can": "python-can", "cv2": "OpenCV", "hdrh": "HdrHistogram"}
"""Import name -> the distribution's name as the import table spells it (others: the same)."""


def product_files() -> list[str]:
    """Every module and data file of the product packages, as ``package/.../name``."""
    return sorted(
        p.relative_to(ROOT).as_posix()
        for pkg in PACKAGES
        for p in (ROOT / pkg).rglob("*")
        if p.suffix in SUFFIXES and p.name != "__init__.py" and "__pycache__" not in p.parts
    )


def findable(rel: str, lines: list[str], ambiguous: set[str]) -> bool:
    """``rel`` is named on a line of the doc: by its file name when no other product file has
    that name; else by ``folder/name``, or by its name on a line that names its folder (a
    top-level module by its whole path). A subcommand's module: by ``COMMAND_MODULES``."""
    p = PurePosixPath(rel)
    if p.parent.as_posix() == "rt_controller/commands" and p.stem in COMMAND_MODULES:
        return True
    name = re.compile(rf"[`/ ]{re.escape(p.name)}\b")
    if p.name not in ambiguous:
        return any(name.search(line) for line in lines)
    if len(p.parts) == 2:
        return any(rel in line for line in lines)
    short = f"{p.parent.name}/{p.name}"
    return any(short in ln or (name.search(ln) and f"{p.parent}/" in ln) for ln in lines)


def test_every_product_module_is_findable_from_the_architecture_doc():
    lines = DOC.read_text(encoding="utf-8").splitlines()
    files = product_files()
    names = [PurePosixPath(f).name for f in files]
    ambiguous = {n for n in names if names.count(n) > 1}
    missing = [f for f in files if not findable(f, lines, ambiguous)]
    assert len(files) > 150 and not missing, missing


def import_table_row(package: str) -> str:
    """``package``'s row of the table under "Who may import whom"."""
    text = DOC.read_text(encoding="utf-8")
    lines = text[text.index("## Who may import whom") :].splitlines()
    return next(ln for ln in lines if ln.startswith(f"| `{package}/` |"))


def third_party_imports(package: str) -> set[str]:
    std = set(sys.stdlib_module_names) | {"__future__"}
    return {
        name
        for path in (ROOT / package).rglob("*.py")
        for name in imported_packages(path)
        if name not in std and name not in PACKAGES
    }


def test_the_import_table_names_every_library_a_lower_package_imports():
    """hal, vision and plant_emulator: what they import of the world is in their row."""
    offenders = {
        package: sorted(lib for lib in libs if DIST_NAMES.get(lib, lib) not in row)
        for package in ("hal", "plant_emulator", "vision")
        if (row := import_table_row(package))
        if (libs := third_party_imports(package))
    }
    assert not any(offenders.values()), offenders


def drawn_edges() -> set[tuple[str, str]]:
    """The solid ``A --> B`` arrows between product packages of the doc's import graph."""
    text = DOC.read_text(encoding="utf-8")
    graph = text[text.index("```mermaid\ngraph BT") :].split("```", 2)[1]
    arrows = re.findall(r"^\s*(\w+) --> (\w+)\s*$", graph, flags=re.M)
    return {(a, b) for a, b in arrows if a in PACKAGES and b in PACKAGES}


def test_the_import_graph_draws_every_import_between_packages():
    """The subcommands that dispatch to the emulator are drawn apart (a dotted arrow)."""
    edges = {
        (pkg, dep)
        for pkg in PACKAGES
        for path in (ROOT / pkg).rglob("*.py")
        if path.relative_to(ROOT).as_posix() not in CLI_DISPATCH
        for dep in imported_packages(path)
        if dep in PACKAGES and dep != pkg
    }
    assert edges == drawn_edges()
