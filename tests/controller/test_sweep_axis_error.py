"""``hil sweep``: an invalid axis value gives one line that names its key once."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest


def _sweep(spec: Path, out: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "rt_controller.cli", "sweep", str(spec), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.mark.parametrize(
    ("values", "reason"),
    [("[-1.0]", "must be positive"), ('["a"]', "expected a number, got 'a'")],
)
def test_an_invalid_axis_value_names_its_key_once(tmp_path: Path, values: str, reason: str):
    spec = tmp_path / "bad.toml"
    spec.write_text(f'[study]\nduration_s = 1.0\n[[axes]]\nkey = "gains.kp"\nvalues = {values}\n')
    proc = _sweep(spec, tmp_path / "out")
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("hil sweep: error: ")
    assert lines[0].count("gains.kp") == 1
    assert reason in lines[0]
    assert not (tmp_path / "out").exists()
