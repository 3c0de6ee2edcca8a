"""DESIGN.md's dependency directions, checked on the source: hal imports neither package above
it; plant_emulator and rt_controller never import each other, except that the ``hil`` CLI's
subcommands dispatch to the emulator's entry points."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CLI_DISPATCH = {
    "rt_controller/commands/emulator.py",
    "rt_controller/commands/simulate.py",
    "rt_controller/commands/vision.py",
}
FORBIDDEN = {
    "hal": {"rt_controller", "plant_emulator"},
    "plant_emulator": {"rt_controller"},
    "rt_controller": {"plant_emulator"},
}


def imported_packages(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_dependency_directions(package: str):
    offenders = []
    for path in sorted((ROOT / package).rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        bad = imported_packages(path) & FORBIDDEN[package]
        if bad and rel not in CLI_DISPATCH:
            offenders.append(f"{rel} imports {', '.join(sorted(bad))}")
    assert not offenders, offenders


def test_the_checker_sees_imports(tmp_path: Path):
    probe = tmp_path / "probe.py"
    probe.write_text("import plant_emulator.world\nfrom rt_controller.control.model import X\n")
    assert imported_packages(probe) == {"plant_emulator", "rt_controller"}
