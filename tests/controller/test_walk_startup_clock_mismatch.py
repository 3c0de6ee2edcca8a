"""A standalone ``hil controller`` whose clock does not match the emulator's: the run's error
points at the cause (the emulator's ``--lockstep``) when the controller can tell, from the
frames it sees, which clock the DSP runs."""

from __future__ import annotations

import pytest

from hal.bus import isolated_spec
from tests.support import free_endpoint, run_hil, start_hil, stop_hil
from tests.support.proc import WAIT_S

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def _controller(can: str, endpoint: str, log, *extra: str):
    args = ["controller", "--can", can, "--zenoh-endpoint", endpoint, "--no-rt"]
    return run_hil([*args, "--duration", "1", "--log", str(log), *extra], timeout_s=WAIT_S)


def test_a_lockstep_controller_on_a_realtime_emulator_asks_for_lockstep(tmp_path):
    """The DSP's joint states arrive, its Sync frames never do: the emulator runs realtime."""
    can, endpoint = isolated_spec("udp_multicast"), free_endpoint()
    emulator = start_hil(["emulator", "--can", can, "--zenoh-endpoint", endpoint])
    try:
        done = _controller(can, endpoint, tmp_path / "run.mcap", "--clock", "lockstep")
    finally:
        stop_hil(emulator)
    assert done.returncode == 1, done.stderr
    assert "no Sync from the DSP for 30 s" in done.stderr, done.stderr
    assert "is the emulator started with --lockstep?" in done.stderr, done.stderr


def test_a_realtime_controller_on_a_lockstep_emulator_names_the_clock(tmp_path):
    """The DSP's Sync frames arrive, the features never do (a lockstep world waits for its
    first step): the error says the emulator runs lockstep, not only that a peer is missing."""
    can, endpoint = isolated_spec("udp_multicast"), free_endpoint()
    emulator = start_hil(["emulator", "--can", can, "--zenoh-endpoint", endpoint, "--lockstep"])
    vision = start_hil(["vision", "--zenoh-endpoint", endpoint])
    try:
        done = _controller(can, endpoint, tmp_path / "run.mcap", "--clock", "realtime")
    finally:
        stop_hil(vision)
        stop_hil(emulator)
    assert done.returncode != 0, done.stderr
    assert "no image features" in done.stderr, done.stderr
    assert "the DSP runs lockstep" in done.stderr and "--clock lockstep" in done.stderr, done.stderr
