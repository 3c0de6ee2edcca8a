"""``hil param --key-file`` with something other than a key file (a named pipe, a symbolic
link) ends at once with one line naming what it is (exit 2): never a hang waiting for a writer
on the pipe, never a bare errno text."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from hal.secoc import write_key_file

HIL = [sys.executable, "-m", "rt_controller.cli"]
ROOT = Path(__file__).resolve().parents[2]


def _param_get(key: Path) -> subprocess.CompletedProcess[str]:
    cmd = [*HIL, "param", "get", "--key-file", str(key), "--timeout", "1"]
    # the endpoint is never reached: the key is checked first
    cmd += ["--zenoh-endpoint", "tcp/127.0.0.1:9"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=ROOT)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes")
def test_a_named_pipe_is_refused_not_waited_on(tmp_path: Path) -> None:
    pipe = tmp_path / "rig.key"
    os.mkfifo(pipe, 0o600)
    out = _param_get(pipe)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert out.stderr.strip().splitlines() == [
        f"hil param: error: rig key {pipe}: not a regular file"
    ]


def test_a_symbolic_link_is_refused_saying_so(tmp_path: Path) -> None:
    link = tmp_path / "link.key"
    link.symlink_to(write_key_file(tmp_path / "rig.key"))
    out = _param_get(link)
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1
    assert "symbolic link" in out.stderr and str(tmp_path / "rig.key") in out.stderr
