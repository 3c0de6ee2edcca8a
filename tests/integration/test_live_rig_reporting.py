"""The live service's ``hil up`` and :func:`~rt_controller.rig.processes.run_rig` as a user
meets them (natively over CAN on ``udp_multicast`` and zenoh on loopback, each run on ports of
its own): ``hil up --json`` from the command line, and a rig process that cannot start or dies
mid-run reported with its exit status and stderr tail, nothing left running.
"""

from __future__ import annotations

import json
import math
import os
import re
import signal
import time

import pytest

from hal.bus import isolated_spec
from rt_controller.logtools.reader import read_log
from rt_controller.rig.failures import RigProcessError
from rt_controller.rig.processes import Rig, run_rig
from tests.support import free_endpoint, run_hil
from tests.support.live_rig import rig_options, wait_for_cycles
from tests.support.proc import folder_of_a_killed_run, processes_mentioning

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]


def assert_nothing_left(token: str, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while (left := processes_mentioning(token)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not left, f"left running: {left}"


def test_hil_up_json_from_the_command_line(tmp_path):
    """... and the temporary folders a killed ``hil up`` left (its config, its rig key) are
    removed by the next one."""
    left = [folder_of_a_killed_run(prefix) for prefix in ("hil-up-", "hil-rig-key-")]
    ep = free_endpoint()
    log = tmp_path / "cli.mcap"
    args = ["up", "--lockstep", "--duration", "2", "--json", "--law", "ioc"]
    args += ["--can", isolated_spec("udp_multicast"), "--zenoh-endpoint", ep, "--log", str(log)]
    try:
        done = run_hil(args, 120)
    finally:
        assert_nothing_left(ep)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    for key in ("J", "f_final", "ticks", "deadline_misses", "solve_us_p99", "log"):
        assert key in summary, key
    assert summary["ticks"] == 100 and summary["log"] == str(log) and log.exists()
    assert len(summary["f_final"]) == 2 and math.isfinite(summary["J"])
    assert summary["exit_codes"] == {"controller": 0, "vision": 0, "emulator": 0}
    assert read_log(log, raw=False).n_cycles == 100
    assert not any(folder.exists() for folder in left), left


def test_hil_up_reports_a_process_that_cannot_start(tmp_path):
    """A CAN interface that is not there (the spec itself is sound, so ``hil up`` cannot tell
    before the processes open it): the emulator (or controller) exits 2; ``hil up`` names it
    with its exit status and stderr tail, exits non-zero, and leaves nothing running."""
    ep = free_endpoint()
    args = ["up", "--lockstep", "--duration", "2", "--json", "--can", "socketcan:hilnone0"]
    args += ["--zenoh-endpoint", ep, "--log", str(tmp_path / "bad.mcap")]
    try:
        done = run_hil(args, 120)
    finally:
        assert_nothing_left(ep)
    assert done.returncode == 2, (done.stdout, done.stderr)
    # after the warning a bus that may hold hardware gets (an emulated DSP starts on it)
    err = done.stderr.split("\n", 1)[1] if done.stderr.startswith("hil up: warning:") else ""
    assert err.startswith("hil up: error:"), done.stderr
    m = re.search(r"(emulator|vision|controller) exited with status (-?\d+)", err)
    assert m and m.group(2) == "2", err
    assert f"hil {m.group(1)}: error:" in err  # the stderr tail of the process that died
    assert not done.stdout.strip().startswith("{")


def test_pixel_noise_the_rendering_camera_cannot_apply_is_refused(tmp_path):
    """camera.noise_px is the analytic camera's; on the rendering camera nothing applied it and
    the run went on as if noise-free. The emulator refuses it in one line, and so does hil up."""
    config = tmp_path / "noisy.toml"
    config.write_text("[camera]\nnoise_px = 0.5\n", encoding="utf-8")
    ep = free_endpoint()
    args = ["up", "--lockstep", "--duration", "1", "--config", str(config), "--json"]
    args += ["--can", isolated_spec("udp_multicast"), "--zenoh-endpoint", ep]
    try:
        done = run_hil([*args, "--log", str(tmp_path / "noisy.mcap")], 120)
    finally:
        assert_nothing_left(ep)
    assert done.returncode == 2, (done.stdout, done.stderr[-2000:])
    assert "emulator exited with status 2" in done.stderr, done.stderr
    assert "camera.noise_px = 0.5 is the analytic camera's pixel noise" in done.stderr


def test_run_rig_reports_an_emulator_killed_mid_run(tmp_path):
    log = tmp_path / "emu-killed.mcap"
    opts = rig_options(log, law="ioc", lockstep=True, duration_s=600.0)
    with Rig(opts) as rig:
        rig.start()
        children = list(rig.children)
        wait_for_cycles(log, 50, rig)
        emu = next(c for c in rig.children if c.name == "emulator")
        os.kill(emu.proc.pid, signal.SIGKILL)
        with pytest.raises(RigProcessError) as info:
            rig.wait_controller()
        message = str(info.value)
        assert message.startswith("emulator killed by SIGKILL"), message
        assert info.value.end.name == "emulator" and info.value.end.returncode == -signal.SIGKILL
        assert "hil emulator: serving the arm on" in message  # its stderr tail
    # the context manager stopped the others; the conftest fixture checks for leaks as well
    assert len(children) == 3 and all(c.proc.returncode is not None for c in children)
    assert_nothing_left(opts.zenoh_endpoint)
    loaded = read_log(log)  # the controller was stopped with SIGTERM: a finished file
    assert loaded.n_cycles >= 50 and not loaded.truncated


def test_run_rig_bad_spec_raises_naming_the_process(tmp_path):
    opts = rig_options(tmp_path / "x.mcap", can="nosuchbus:0", lockstep=True, duration_s=2.0)
    with pytest.raises(RigProcessError, match=r"(emulator|controller) exited with status 2"):
        run_rig(opts)
    assert_nothing_left(opts.zenoh_endpoint)
