"""A standalone lockstep ``hil controller`` without ``--duration`` ends when the DSP's Sync
frames stop for 2 s (the emulator finished). When none came at all, that is no clean end of a
run: the error says what it waited for and what to start."""

from __future__ import annotations

import pytest

from hal.bus import isolated_spec
from tests.support import free_endpoint, run_hil, start_hil, stop_hil
from tests.support.proc import WAIT_S

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def test_no_sync_ever_without_a_duration_names_what_is_missing(tmp_path):
    """A realtime emulator: its joint states arrive, its Sync frames never do."""
    can, endpoint = isolated_spec("udp_multicast"), free_endpoint()
    emulator = start_hil(["emulator", "--can", can, "--zenoh-endpoint", endpoint])
    try:
        args = ["controller", "--can", can, "--zenoh-endpoint", endpoint, "--no-rt"]
        done = run_hil(
            [*args, "--clock", "lockstep", "--log", str(tmp_path / "run.mcap")], timeout_s=WAIT_S
        )
    finally:
        stop_hil(emulator)
    assert done.returncode == 1, done.stderr
    assert "no Sync from the DSP" in done.stderr, done.stderr
    assert "hil emulator --lockstep" in done.stderr, done.stderr
    assert "is the emulator started with --lockstep?" in done.stderr, done.stderr
