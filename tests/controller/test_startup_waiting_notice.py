"""A ``hil controller`` whose inputs do not come says once, after about 2 s, what it waits
for, on which transports and for how long at most, instead of staying silent until the
start-up timeout's error; a start whose inputs come at once says nothing more than before."""

from __future__ import annotations

import pytest

from hal.bus import isolated_spec
from tests.support import free_endpoint, run_hil, start_hil, stop_hil
from tests.support.proc import WAIT_S

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def test_a_bus_without_a_dsp_says_what_it_waits_for_before_the_error(tmp_path):
    """The emulator (the zenoh hub) on another udp_multicast group: no joint state, no
    features (no vision)."""
    other_can, can, endpoint = (
        isolated_spec("udp_multicast"),
        isolated_spec("udp_multicast"),
        free_endpoint(),
    )
    emulator = start_hil(["emulator", "--can", other_can, "--zenoh-endpoint", endpoint])
    try:
        args = ["controller", "--can", can, "--zenoh-endpoint", endpoint, "--no-rt"]
        done = run_hil([*args, "--log", str(tmp_path / "run.mcap")], timeout_s=WAIT_S)
    finally:
        stop_hil(emulator)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.splitlines()
    waiting = [i for i, line in enumerate(lines) if "waiting for" in line]
    error = [i for i, line in enumerate(lines) if "no joint state (CAN) within 20 s" in line]
    assert len(waiting) == 1 and error and waiting[0] < error[0], done.stderr
    assert lines[waiting[0]] == (
        f"hil controller: waiting for the first joint state on CAN {can} and image features "
        f"on zenoh {endpoint} (up to 20 s)"
    ), done.stderr


def test_a_start_whose_inputs_come_says_nothing_more(tmp_path):
    """A lockstep emulator and vision: the first joint state comes at once."""
    can, endpoint = isolated_spec("udp_multicast"), free_endpoint()
    common = ["--can", can, "--zenoh-endpoint", endpoint]
    emulator = start_hil(["emulator", *common, "--lockstep"])
    vision = start_hil(["vision", "--zenoh-endpoint", endpoint, "--wait", "60"])
    try:
        args = ["controller", *common, "--no-rt", "--clock", "lockstep", "--duration", "1"]
        done = run_hil([*args, "--log", str(tmp_path / "run.mcap")], timeout_s=WAIT_S)
    finally:
        stop_hil(vision)
        stop_hil(emulator)
    assert done.returncode == 0, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.startswith("hil controller:")]
    assert len(lines) == 1 and lines[0].startswith("hil controller: law "), done.stderr


def test_inputs_signed_with_another_key_are_named_as_such(tmp_path):
    """The emulator and vision on the rig key, the controller on another: every frame and
    feature message arrives and is refused (bad_mac). The notice and the error say so and
    name the likeliest cause, not "is hil emulator running?"."""
    can, endpoint = isolated_spec("udp_multicast"), free_endpoint()
    other = tmp_path / "other.key"
    assert run_hil(["keygen", str(other)], timeout_s=WAIT_S).returncode == 0
    emulator = start_hil(["emulator", "--can", can, "--zenoh-endpoint", endpoint])
    vision = start_hil(["vision", "--zenoh-endpoint", endpoint, "--wait", "60"])
    try:
        args = ["controller", "--can", can, "--zenoh-endpoint", endpoint, "--no-rt"]
        args += ["--key-file", str(other), "--log", str(tmp_path / "run.mcap")]
        done = run_hil(args, timeout_s=WAIT_S)
    finally:
        stop_hil(vision)
        stop_hil(emulator)
    assert done.returncode == 2, done.stderr
    error = done.stderr.strip().splitlines()[-1]
    assert error.startswith("hil controller: error: no joint state (CAN) within 20 s: "), error
    assert "DSP frames rejected (bad_mac " in error, error
    assert error.endswith("signed with another rig key? (every process needs the same --key-file)")
    assert "is `hil emulator`" not in error, error
