"""Two rigs on one host: a live-view port another monitor (or rig) already serves is refused in
one line that names what is taken and the option that chooses another, for `hil up --monitor`
and for a second `hil monitor`."""

from __future__ import annotations

import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from hal.config import load_config
from hal.secoc import write_key_file
from hal.zenoh_session import free_loopback_port, open_session
from tests.support import REPO, run_hil


@pytest.fixture
def taken_port() -> Iterator[int]:
    """A loopback port a server listens on (another rig's live view)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen(1)
        yield sock.getsockname()[1]


def test_hil_up_names_the_option_for_another_monitor_port(taken_port: int) -> None:
    out = run_hil(["up", "--monitor-port", str(taken_port), "--duration", "1"], timeout_s=60)
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr
    assert lines[0].startswith("hil up: error: --monitor: cannot listen on 127.0.0.1:")
    assert f":{taken_port}: Address already in use" in lines[0]
    assert "--monitor-port PORT" in lines[0]


def test_a_second_hil_monitor_names_the_option_for_another_port(
    taken_port: int, tmp_path: Path
) -> None:
    key = write_key_file(tmp_path / "rig.key")
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    hub = open_session(load_config(None), listen=True, endpoint=endpoint)
    try:
        out = subprocess.run(
            [
                sys.executable, "-m", "rt_controller.cli", "monitor", "--key-file", str(key),
                "--zenoh-endpoint", endpoint, "--port", str(taken_port), "--duration", "1",
            ],
            capture_output=True,
            text=True,
            timeout=120,
            cwd=REPO,
        )  # fmt: skip
    finally:
        hub.close()
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr
    assert lines[0].startswith(
        f"hil monitor: error: cannot serve Foxglove WebSocket on 127.0.0.1:{taken_port}"
    )
    assert "in use" in lines[0] and "--port PORT" in lines[0]


def test_frames_of_another_controller_are_named_as_such() -> None:
    """Two `hil controller` on one emulator: each sees the other's TorqueCommands (its own ids,
    counted ``ignored``) and the DSP rejects the interleaved streams; the problem says why."""
    from rt_controller.runtime.counters import run_problems

    summary = {"rejections": {"dsp_rejected_frames": 236, "can_rx": {"ignored": 243}}}
    (problem,) = run_problems(summary)
    assert problem.startswith("the DSP rejected 236 frame(s) (DspStatus.RejectedFrames)")
    assert "243 frame(s) with this controller's own ids from another node" in problem
    assert "another controller on this bus" in problem
    alone = {"rejections": {"dsp_rejected_frames": 236, "can_rx": {"ignored": 0}}}
    assert run_problems(alone) == ["the DSP rejected 236 frame(s) (DspStatus.RejectedFrames)"]
