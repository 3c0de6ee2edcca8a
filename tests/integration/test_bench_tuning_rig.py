"""``hil bench tuning`` with a real rig: a rig that fails says why (its stderr's tail), and the
default run leaves nothing in the user's working directory nor in the temporary folder.

Only the shape and the words are checked: latencies depend on the machine and are never asserted.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def _hil(args: list[str], cwd: Path, tmp: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "TMPDIR": str(tmp)}
    return subprocess.run(
        [sys.executable, "-m", "rt_controller.cli", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
    )


def test_a_rig_that_fails_gives_its_reason(tmp_path: Path) -> None:
    work = tmp_path / "work"
    (work / "tuning.mcap").mkdir(parents=True)  # hil up refuses a log path that is a folder
    done = _hil(
        ["bench", "tuning", "--workdir", str(work), "--requests", "1", "-q"], tmp_path, tmp_path
    )
    assert done.returncode != 0
    assert "Traceback" not in done.stderr
    assert done.stderr.startswith("hil bench tuning: error: rig (hil up) exited with status 2")
    assert "is a directory, not a file" in done.stderr  # hil up's own reason, from its stderr


def test_the_default_run_leaves_no_folder_behind(tmp_path: Path) -> None:
    cwd, tmp = tmp_path / "cwd", tmp_path / "tmp"
    cwd.mkdir()
    tmp.mkdir()
    done = _hil(["bench", "tuning", "--requests", "1", "-q"], cwd, tmp)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["requests"] == 1 and result["rig_exit"] == 0
    assert result["log"] is None and result["stderr_tail"] == ""
    assert list(cwd.iterdir()) == []
    assert [p.name for p in tmp.iterdir() if p.name.startswith("hil-bench-tuning-")] == []


def test_an_explicit_workdir_is_kept(tmp_path: Path) -> None:
    work = tmp_path / "kept"
    done = _hil(
        ["bench", "tuning", "--workdir", str(work), "--requests", "1", "-q"], tmp_path, tmp_path
    )
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["log"] == str(work / "tuning.mcap")
    assert (work / "tuning.mcap").is_file() and (work / "bench.key").is_file()
