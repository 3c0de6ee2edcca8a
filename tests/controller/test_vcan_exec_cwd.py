"""``scripts/vcan_pytest.py --exec`` runs the command in the caller's working directory (so
``--key-file rig.key`` and the logs it writes are the caller's), natively and inside user-mode
Linux, and refuses a directory the UML guest cannot see. Only the vcan-marked test boots."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.vcan import requires_vcan

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts/vcan_pytest.py"


def _scripts(monkeypatch: pytest.MonkeyPatch):
    """The script's modules ``vcan_host`` and ``vcan_uml`` (they import each other by name)."""
    monkeypatch.syspath_prepend(str(ROOT / "scripts"))
    import vcan_host
    import vcan_uml

    return vcan_host, vcan_uml


def test_the_guest_init_script_enters_the_directory_it_is_given(tmp_path, monkeypatch):
    _, vcan_uml = _scripts(monkeypatch)
    where = tmp_path / "user folder"
    init = vcan_uml.write_init_script(tmp_path, ["hil", "--help"], {}, None, cwd=where)
    assert f"cd '{where}' ||" in init.read_text()


def test_exec_from_a_directory_the_guest_mounts_over_is_refused_in_one_line(monkeypatch):
    missing = _scripts(monkeypatch)[0].uml_missing()
    if missing:
        pytest.skip(f"user-mode Linux is not installed: {', '.join(missing)}")
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--mode", "uml", "--timeout", "60", "--exec", "--", "true"],
        cwd="/proc",
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        "vcan_pytest: error: user-mode Linux cannot see the current directory /proc (the guest "
        "mounts its own /proc); run from another directory"
    ]


@pytest.mark.vcan
@requires_vcan
def test_exec_runs_the_command_in_the_callers_directory(tmp_path):
    code = "import os; print(os.getcwd())"
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--exec", "--", sys.executable, "-c", code],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == str(tmp_path.resolve())
