"""The dependency directions of docs/architecture.md, checked on the source: hal imports neither
package above it; plant_emulator and rt_controller never import each other, except that the
``hil`` CLI's subcommands dispatch to the emulator's entry points."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CLI_DISPATCH = {
    "rt_controller/commands/camera.py",
    "rt_controller/commands/emulator.py",
    "rt_controller/commands/simulate.py",
    "rt_controller/commands/sweep.py",
    "rt_controller/commands/vision.py",
}
FORBIDDEN = {
    "hal": {"rt_controller", "plant_emulator"},
    "plant_emulator": {"rt_controller"},
    "rt_controller": {"plant_emulator"},
    "vision": {"rt_controller", "plant_emulator"},
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


def test_product_code_never_imports_the_tests():
    """The test oracles (the Python rule, the NumPy solver) live in tests/support/ only."""
    offenders = [
        path.relative_to(ROOT).as_posix()
        for package in sorted(FORBIDDEN)
        for path in sorted((ROOT / package).rglob("*.py"))
        if "tests" in imported_packages(path)
    ]
    assert not offenders, offenders


def test_the_checker_sees_imports(tmp_path: Path):
    probe = tmp_path / "probe.py"
    probe.write_text(
        "import plant_emulator.world\nfrom rt_controller.control.model import X\n"
        "from tests.support.python_rule import PythonRule\n"
    )
    assert imported_packages(probe) == {"plant_emulator", "rt_controller", "tests"}


# ------------------------------------------------------------ rt_controller's own layers

IO_MODULES = (
    "can",
    "zenoh",
    "mcap",
    "cantools",
    "hal.bus",
    "hal.joint_client",
    "hal.zenoh_session",
    "hal.udp_loopback",
    "rt_controller.runtime.recorder",
    "rt_controller.runtime.daemon",
    "rt_controller.runtime.hardware",
    "rt_controller.runtime.loop",
    "rt_controller.runtime.pacers",
    "rt_controller.logtools",
    "rt_controller.logs",
)
"""What the pure control layer (``rt_controller/control/``) must not import."""


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def imported_modules(path: Path) -> set[str]:
    """Every module ``path`` imports, at any depth (lazy imports count), as dotted names;
    ``from pkg import name`` yields ``pkg.name`` when that is a module of ours."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
            out.update(f"{node.module}.{alias.name}" for alias in node.names)
    return out


def import_graph(package: str = "rt_controller") -> dict[str, set[str]]:
    modules = {module_name(p): p for p in sorted((ROOT / package).rglob("*.py"))}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        graph[name] = {m for m in imported_modules(path) if m in modules and m != name}
    return graph


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every elementary cycle found by a depth-first search (one per back edge)."""
    cycles: list[list[str]] = []
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> None:
        state[node] = 1
        stack.append(node)
        for dep in sorted(graph.get(node, ())):
            if state.get(dep) == 1:
                cycles.append([*stack[stack.index(dep) :], dep])
            elif dep not in state:
                visit(dep)
        stack.pop()
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node)
    return cycles


def test_no_import_cycles_in_rt_controller():
    assert find_cycles(import_graph()) == []


def test_the_cycle_finder_finds_cycles():
    assert find_cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == [["a", "b", "c", "a"]]
    assert find_cycles({"a": {"b"}, "b": set()}) == []


def test_control_layer_does_no_io():
    offenders = []
    for path in sorted((ROOT / "rt_controller" / "control").rglob("*.py")):
        for mod in imported_modules(path):
            if any(mod == io or mod.startswith(io + ".") for io in IO_MODULES):
                offenders.append(f"{path.relative_to(ROOT).as_posix()} imports {mod}")
    assert not offenders, offenders


def test_cli_does_not_import_the_commands_it_registers():
    assert not {
        m for m in import_graph()["rt_controller.cli"] if m.startswith("rt_controller.commands")
    }


def test_experiment_runner_does_not_use_cli_modules():
    rig = [m for m in import_graph() if m.startswith("rt_controller.rig")]
    offenders = [
        (m, d) for m in rig for d in import_graph()[m] if d.startswith("rt_controller.commands")
    ]
    assert not offenders, offenders


OFFLINE_LAYERS = ("rt_controller.logtools", "rt_controller.logs")
"""The offline log readers: below the commands, the rig and the CLI."""
ANALYSIS_EXTRA = ("pandas", "pyarrow", "scipy")
"""The ``analysis`` extra: the core rig runs without it, so no module imports it at load time."""


def test_offline_log_layers_stay_below_the_commands():
    graph = import_graph()
    above = ("rt_controller.commands", "rt_controller.rig", "rt_controller.cli")
    offenders = [
        (m, d)
        for m in graph
        if m.startswith(OFFLINE_LAYERS)
        for d in graph[m]
        if d.startswith(above)
    ]
    assert not offenders, offenders


def test_calibration_stays_below_the_loop_and_the_log_tools():
    graph = import_graph()
    above = (
        "rt_controller.runtime",
        "rt_controller.logtools",
        "rt_controller.commands",
        "rt_controller.rig",
        "rt_controller.cli",
    )
    calibration = [m for m in graph if m.startswith("rt_controller.calibration")]
    assert calibration, "the calibration package moved: update this test"
    offenders = [(m, d) for m in calibration for d in graph[m] if d.startswith(above)]
    assert not offenders, offenders


def top_level_imports(path: Path) -> set[str]:
    """Modules imported when ``path`` is loaded: its top-level statements (and those nested in
    top-level ``if``/``try`` blocks), except under ``if TYPE_CHECKING:``."""
    names: set[str] = set()

    def walk(body: list[ast.stmt]) -> None:
        for node in body:
            if isinstance(node, ast.Import):
                names.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names.add(node.module)
            elif isinstance(node, ast.If):
                if not (isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING"):
                    walk(node.body)
                walk(node.orelse)
            elif isinstance(node, ast.Try):
                walk(node.body)
                for handler in node.handlers:
                    walk(handler.body)
                walk(node.orelse)
                walk(node.finalbody)

    walk(ast.parse(path.read_text(), filename=str(path)).body)
    return names


@pytest.mark.parametrize("package", ["hal", "rt_controller"])
def test_the_analysis_extra_is_imported_lazily(package: str):
    offenders = []
    for path in sorted((ROOT / package).rglob("*.py")):
        for mod in top_level_imports(path):
            if mod.split(".")[0] in ANALYSIS_EXTRA:
                offenders.append(f"{path.relative_to(ROOT).as_posix()} imports {mod}")
    assert not offenders, offenders


def test_the_top_level_checker_skips_functions_and_type_checking(tmp_path: Path):
    probe = tmp_path / "probe.py"
    probe.write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import pandas\n"
        "try:\n    import scipy\nexcept ImportError:\n    pass\n"
        "def f():\n    import pyarrow\n"
    )
    assert top_level_imports(probe) == {"typing", "scipy"}


def test_law_codes_match_the_config_names():
    from hal.config import LAW_NAMES
    from rt_controller.control.decide_kernel import LAW_CODES
    from tests.support.python_laws import LAWS

    assert tuple(LAW_CODES) == tuple(LAWS) == LAW_NAMES


def test_sweep_package_uses_no_cli_modules():
    """rt_controller.sweep sits beside rig/ and below commands/: commands/sweep.py hands the
    simulate engine its plant, so the package imports neither the commands nor the emulator."""
    graph = import_graph()
    offenders = [
        (m, d)
        for m in graph
        if m.startswith("rt_controller.sweep")
        for d in graph[m]
        if d.startswith("rt_controller.commands") or d == "rt_controller.cli"
    ]
    assert not offenders, offenders


# ------------------------------------------------------------ the vision pipeline sees pixels

POSE_OR_TRUTH = {
    "PoseMsg",
    "PoseDecoder",
    "decode_pose",
    "encode_pose",
    "KEY_CAMERA_POSE",
    "camera_pose",
    "scenario",
    "f0",
    "f_jump",
    "paper_target",
    "plant",
    "plant_view",
}
"""Names through which code could learn the camera's pose or the target's true position."""


def pose_or_truth_names(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.Attribute):
            names.add(node.attr)
        elif isinstance(node, ast.Name):
            names.add(node.id)
    return names & POSE_OR_TRUTH


def test_the_vision_pipeline_sees_only_pixels():
    """vision/ measures f from frames: it imports neither the emulator nor the controller
    (test_dependency_directions), and never touches the camera pose or the scenario's target."""
    offenders = {
        path.relative_to(ROOT).as_posix(): sorted(bad)
        for path in sorted((ROOT / "vision").rglob("*.py"))
        if (bad := pose_or_truth_names(path))
    }
    assert not offenders, offenders


def test_the_pose_checker_sees_a_pose(tmp_path: Path):
    probe = tmp_path / "probe.py"
    probe.write_text("from hal.vision_codec import PoseMsg\nx = cfg.scenario.f0\n")
    assert pose_or_truth_names(probe) == {"PoseMsg", "scenario", "f0"}


MAX_FILE_LINES = 500
"""No source file of the project (product, scripts, tests) is longer: a module past it does
more than one thing and is split by concern."""


def test_no_source_file_is_over_500_lines():
    skip = {".venv", "site", "build", "node_modules"}
    files = [p for p in ROOT.rglob("*.py") if not skip & set(p.relative_to(ROOT).parts[:1])]
    long = {
        str(p.relative_to(ROOT)): n
        for p in files
        if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_FILE_LINES
    }
    assert len(files) > 300 and not long, long
