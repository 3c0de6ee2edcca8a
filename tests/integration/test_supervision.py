"""``hil up`` owns its children: a signal to it, or its death, stops all of them (controller
first: torque off, log finished) and nothing is left running.

Each test starts the real ``hil up`` as a separate process in a session of its own, injects the
fault and then waits (polling, no wall-clock assertion) until no process of the rig is left.
"""

from __future__ import annotations

import os
import signal
import subprocess
from pathlib import Path

import pytest

from hal.can_codec import DspCodec
from hal.can_frames import TorqueCommand
from hal.zenoh_session import free_loopback_port
from rt_controller.logtools.reader import read_log
from rt_controller.logtools.republish import can_message
from tests.support import cycles_logged, start_hil_up
from tests.support.proc import WAIT_S, processes_mentioning, wait_for

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]


def _children(ep: str) -> list[str]:
    return [p for p in processes_mentioning(ep) if " up " not in p]


def _finish(proc: subprocess.Popen, ep: str) -> tuple[int, str]:
    try:
        _, err = proc.communicate(timeout=WAIT_S)
    finally:
        if proc.poll() is None:  # pragma: no cover - only on a hang
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
        wait_for(lambda: not processes_mentioning(ep), "every rig process to end")
    return proc.returncode, err


def last_torque(can_tx: list[dict]) -> tuple[float, float]:
    """(Tau1, Tau2) of the last TorqueCommand the controller sent, decoded by the DSP's codec."""
    codec, last = DspCodec(verify=False), None  # a log: its run's key is gone
    for rec in can_tx:
        frame = codec.decode_command(can_message(rec), 0)
        if isinstance(frame, TorqueCommand):
            last = (frame.tau1, frame.tau2)
    assert last is not None, "no torque command in the log"
    return last


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT, signal.SIGHUP])
def test_a_signal_to_hil_up_stops_the_rig_torque_first(tmp_path, sig):
    ep, log = f"tcp/127.0.0.1:{free_loopback_port()}", tmp_path / "run.mcap"
    proc = start_hil_up(ep, log, "--duration", "600", "--lockstep")
    wait_for(lambda: len(_children(ep)) == 3, "three children", proc)
    wait_for(lambda: cycles_logged(log) >= 20, "the controller's first ticks", proc)
    proc.send_signal(sig)
    rc, err = _finish(proc, ep)
    assert rc == 128 + sig, err
    last = err.strip().splitlines()[-1]
    assert f"interrupted by {sig.name}" in last and last.startswith("hil up:"), err
    data = read_log(log)
    assert not data.truncated  # the controller finished its log
    assert data.n_cycles >= 20
    assert last_torque(data.can_tx) == (0.0, 0.0)  # torque off before the rig went down


def test_sigterm_during_start_up_stops_cleanly(tmp_path):
    """Before the controller has armed the DSP: exit 143 with one line, nothing left, and no
    misleading "no hub" error from a child told to stop while it waited."""
    ep, log = f"tcp/127.0.0.1:{free_loopback_port()}", tmp_path / "run.mcap"
    proc = start_hil_up(ep, log, "--duration", "600")
    wait_for(lambda: len(_children(ep)) == 3, "three children", proc)
    proc.send_signal(signal.SIGTERM)
    rc, err = _finish(proc, ep)
    assert rc == 143, err
    assert "interrupted by SIGTERM" in err.strip().splitlines()[-1], err
    assert "no hub" not in err and "Traceback" not in err, err


def test_a_killed_hil_up_leaves_nothing_running(tmp_path):
    """SIGKILL cannot be caught: the children learn of their parent's death from the kernel
    (parent-death signal), stop on their own and the controller still finishes its log."""
    ep, log = f"tcp/127.0.0.1:{free_loopback_port()}", tmp_path / "run.mcap"
    proc = start_hil_up(ep, log, "--duration", "600", "--lockstep")
    wait_for(lambda: len(_children(ep)) == 3, "three children", proc)
    wait_for(lambda: cycles_logged(log) >= 20, "the controller's first ticks", proc)
    proc.kill()  # only hil up itself, not its process group
    proc.communicate()
    wait_for(lambda: not processes_mentioning(ep), "the orphaned children to stop")
    assert not read_log(log).truncated
