"""Ctrl-C to a ``hil sweep`` on the rig engine: when it exits, no process it started runs.

The rig's processes are grandchildren (a Dask worker starts them, in a process group of their
own, so a terminal's SIGINT does not reach them): the sweep must stop them and wait."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.proc import alive, children_of, reaped, wait_for

pytestmark = pytest.mark.integration

SPEC = """
[study]
engine = "rig"
duration_s = 600.0
timeout_s = 900.0
[base.camera]
model = "analytic"
[[axes]]
key = "gains.kp"
values = [0.13, 0.14]
"""


def _argv(pid: int) -> list[bytes]:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return []


def _descendants(pid: int) -> list[int]:
    out, todo = [], children_of(pid)
    while todo:
        child = todo.pop()
        out.append(child)
        todo += children_of(child)
    return out


def _controller(pid: int) -> int | None:
    """The pid of the rig's controller under ``pid`` once it has started its recorder."""
    for child in _descendants(pid):
        if b"controller" in _argv(child)[:4] and children_of(child):
            return child
    return None


def test_ctrl_c_leaves_no_rig_process_running(tmp_path: Path):
    spec = tmp_path / "rig.toml"
    spec.write_text(SPEC)
    cmd = [sys.executable, "-m", "rt_controller.cli", "sweep", str(spec), "--workers", "1"]
    cmd += ["--out", str(tmp_path / "out"), "--no-progress"]
    proc = subprocess.Popen(
        cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    with reaped(proc):
        wait_for(lambda: _controller(proc.pid) is not None, "a rig controller", proc)
        # multiprocessing's resource tracker ends on its own once hil has exited: not the rig's
        started = [
            p for p in _descendants(proc.pid) if b"resource_tracker" not in b"".join(_argv(p))
        ]
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C at a terminal: the whole group
        _, err = proc.communicate(timeout=120)
        left = {p: b" ".join(_argv(p)[:4]).decode() for p in started if alive(p)}
        for pid in left:
            os.kill(pid, signal.SIGKILL)
    assert proc.returncode == 130, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    assert not left, f"still running after hil sweep exited: {left}"
    journal = tmp_path / "out" / "rows.jsonl"  # the cut run has no row: a resume runs it
    assert not journal.exists() or not journal.read_text().strip()
