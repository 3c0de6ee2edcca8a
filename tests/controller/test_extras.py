"""A missing extra is one line naming the extra and its pip command, exit 2: through
``extras.require`` / ``require_extra`` and, for a module imported without them, through
``cli.main``. (The same in a real core-only venv: ``tests/integration/test_core_install.py``.)"""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path

import pytest

from rt_controller import extras
from rt_controller.cli import main
from rt_controller.errors import MissingExtraError

ROOT = Path(__file__).resolve().parents[2]
SPEC = ROOT / "examples" / "robustness.toml"


def one_error_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    errors = [line for line in err if ": error: " in line]
    assert len(errors) == 1 and "Traceback" not in "\n".join(err), err
    return errors[0]


@pytest.mark.parametrize(
    "argv",
    [
        ["sweep", str(SPEC)],
        ["experiment", "fig3", "--reps", "1"],
        ["bench", "sweep", "--runs", "1"],
    ],
    ids=lambda a: " ".join(a[:2]),
)
def test_commands_of_the_sweep_extra_name_it(argv, monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "distributed", None)  # `import distributed` fails
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    line = one_error_line(capsys)
    command = " ".join(argv[:2] if argv[0] == "bench" else argv[:1])  # "hil bench sweep"
    assert line.startswith(f"hil {command}: error: this command needs the 'sweep' extra")
    assert line.endswith("pip install 'hil-rhc-visual-servo[sweep]'")
    assert list(tmp_path.iterdir()) == []  # refused before any work


def test_a_stray_import_of_an_extra_module_is_explained_by_the_cli(monkeypatch, capsys):
    import rt_controller.commands.info as info

    def handler(_args):
        import pandas  # noqa: F401 - a code path that forgot extras.require

        return 0

    monkeypatch.setitem(sys.modules, "pandas", None)
    monkeypatch.setattr(info, "run", handler)  # what `hil info` runs, bound at registration
    assert main(["info", "x.mcap"]) == 2
    assert one_error_line(capsys) == (
        "hil info: error: this command needs the 'analysis' extra (pandas is not installed): "
        "pip install 'hil-rhc-visual-servo[analysis]'"
    )


def test_a_missing_core_module_stays_a_traceback():
    exc = ModuleNotFoundError("No module named 'numpy'", name="numpy")
    assert extras.as_missing_extra(exc, "this command") is None


def test_require_imports_or_names_the_extra(monkeypatch):
    assert extras.require("json", "x") is sys.modules["json"]  # not an extra: plain import
    for name in ("scipy", "scipy.io"):  # an earlier test may have imported both
        monkeypatch.setitem(sys.modules, name, None)
    with pytest.raises(MissingExtraError, match=r"mat export needs the 'analysis' extra"):
        extras.require("scipy.io", "mat export")


def test_every_extra_of_pyproject_is_known():
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert set(extras.EXTRAS) <= set(declared["optional-dependencies"])
    assert set(declared["optional-dependencies"]) - set(extras.EXTRAS) == {"test"}
