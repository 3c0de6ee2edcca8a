"""The contract of the controller's hardware seam (:class:`hal.hardware_interface.
HardwareInterface`), one suite over every hardware profile: ``dsp``
(:class:`~rt_controller.runtime.hardware.DspHardware`) and ``cia402``
(:class:`~rt_controller.runtime.cia402_hardware.Cia402Hardware`), each against its emulated
rig (``hil emulator --profile P --lockstep`` and ``hil vision`` as processes) on
``udp_multicast`` (host-local, a private port) and on a real ``vcan0`` (marked ``vcan``, run
by scripts/vcan_pytest.py), as ``tests/hal/test_hal_contract.py`` runs the bus contract over
every transport.

The seam's contract: ``configure`` returns once a live peer answers and raises one clear line
without one; ``activate`` reaches *operation enabled*; ``read`` gives a fresh
:class:`~hal.hardware_interface.Observation` each period; ``write``'s torque takes effect (the
joints move the way it pushes); ``deactivate`` leaves the peer's torque off. The profiles are
built and driven as the daemon does (``runtime/daemon.py``), through public constructors and
the seam's methods only. Nothing asserts on timings.
"""

from __future__ import annotations

import contextlib
import dataclasses
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from hal.bus import isolated_spec
from hal.config import RigConfig, load_config
from hal.errors import HalError
from hal.hardware_interface import HardwareInterface, Observation
from hal.secoc import configure_key, rig_key, write_key_file
from hal.vision_receivers import FeatureDecoder
from hal.zenoh_session import free_loopback_port, open_session
from rt_controller.config_rules import apply_overrides, config_toml
from rt_controller.errors import ControllerError
from rt_controller.runtime import hardware as dsp_profile
from rt_controller.runtime.cadence import MonotonicClock
from rt_controller.runtime.cia402_hardware import Cia402Hardware
from rt_controller.runtime.context import RunContext
from rt_controller.runtime.counters import RunCounters
from rt_controller.runtime.daemon import build_hardware, open_links
from rt_controller.runtime.hardware import DspHardware
from rt_controller.runtime.pacers import LockstepPacer
from tests.support.proc import stop_all
from tests.support.vcan import LOCKSTEP_REPLY_TIMEOUT_S, VCAN_CHANNEL, requires_vcan

pytestmark = pytest.mark.integration

PROFILES = ("dsp", "cia402")
TRANSPORTS = [
    pytest.param("udp_multicast", id="udp_multicast"),
    pytest.param("socketcan", id="socketcan", marks=[pytest.mark.vcan, requires_vcan]),
]
STEP_TIMEOUT_S = 10.0
"""How long one lockstep period may take (generous: shared CPUs, user-mode Linux)."""
NO_PEER_TIMEOUT_S = 2.0
"""The start-up timeout of a ``configure`` with no peer (the product's is 20 s)."""
PUSH = (3.0, 0.4)
"""N m per joint: well inside both joints' limits, enough to move the arm in a few periods."""


def bus_spec(transport: str) -> str:
    return f"socketcan:{VCAN_CHANNEL}" if transport == "socketcan" else isolated_spec(transport)


def rig_config(profile: str, transport: str, tmp: Path) -> tuple[RigConfig, Path, Path]:
    """A lockstep configuration of ``profile`` on a private bus and zenoh port, written to a
    file for the peer's processes, and a fresh rig key; (config with the key, file, key)."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    # the test steps the seam by hand: a period's command can come late on any host
    base = load_config(None).with_overrides(
        {"dsp.lockstep_reply_timeout_s": LOCKSTEP_REPLY_TIMEOUT_S}
    )
    cfg = apply_overrides(
        base,
        profile=profile,
        clock="lockstep",
        can=bus_spec(transport),
        zenoh_endpoint=endpoint,
    )
    cfg_file = tmp / f"{profile}.toml"
    cfg_file.write_text(config_toml(cfg), encoding="utf-8")
    key = write_key_file(tmp / "rig.key")
    return configure_key(cfg, str(key), "test"), cfg_file, key


@contextlib.contextmanager
def emulated_rig(cfg_file: Path, key: Path) -> Iterator[None]:
    """``hil emulator --lockstep`` (the profile's hardware, the zenoh hub) and ``hil vision``,
    stopped (by their own pids) at the end."""
    common = ["--config", str(cfg_file), "--key-file", str(key)]
    cli = [sys.executable, "-m", "rt_controller.cli"]
    procs = [
        subprocess.Popen([*cli, "emulator", *common, "--lockstep"], stdout=subprocess.DEVNULL),
        subprocess.Popen([*cli, "vision", *common, "--wait", "60"], stdout=subprocess.DEVNULL),
    ]
    try:
        yield
    finally:
        stop_all(procs)


@contextlib.contextmanager
def profile_seam(cfg: RigConfig, stop: threading.Event) -> Iterator[HardwareInterface]:
    """The configured profile on its links, as the daemon builds it (:func:`build_hardware`;
    lockstep, no raw log); deactivated and its links closed at the end."""
    ctx = RunContext(cfg, MonotonicClock(), stop, RunCounters(), None)
    features = FeatureDecoder.from_config(cfg.controller, key=rig_key(cfg))
    with open_links(cfg, stop) as (can, session):
        hw = build_hardware(ctx, can, session, features, record_raw=False)
        try:
            yield hw
        finally:
            hw.deactivate()


def arm(hw: HardwareInterface) -> int:
    """``activate`` until armed, as the lockstep pacer calls it; the calls it took."""
    for n in range(1, 2000):
        if hw.activate(time.monotonic_ns()):
            return n
        time.sleep(0.005)
    raise AssertionError("activate never reported armed (and never raised)")


def period(hw: HardwareInterface, judge: LockstepPacer, tau: tuple[float, float]) -> Observation:
    """One lockstep period: the world's next step, the read, the torque answering it."""
    k = hw.step(STEP_TIMEOUT_S)
    assert k is not None, "the world did not step"
    obs = hw.read(time.monotonic_ns(), judge)
    hw.write(tau, sync=k, release_ns=time.monotonic_ns())
    return obs


def peer_after_deactivate(hw: HardwareInterface) -> tuple[bool, bool]:
    """(torque on, faulted) as the peer itself reports them: the DSP's DspStatus answering
    DISABLE (a watchdog trip would also end torque, so it must not be the reason), the
    drives' statusword 0x6041 read by SDO (CiA 402: torque only in *operation enabled*)."""
    if isinstance(hw, Cia402Hardware):
        words = [node.sdo[0x6041].raw for node in hw.master.nodes]
        return any(w & 0x6F == 0x27 for w in words), any(w & 0x08 for w in words)
    assert isinstance(hw, DspHardware)
    deadline = time.monotonic() + STEP_TIMEOUT_S
    while time.monotonic() < deadline:
        hw.dsp.drain(time.monotonic_ns())
        status = hw.dsp.status
        if status is not None and not status.torque_enabled:
            return False, status.watchdog_tripped
        time.sleep(0.005)
    return True, False


@pytest.fixture(params=TRANSPORTS)
def transport(request: pytest.FixtureRequest) -> str:
    return request.param


@pytest.mark.parametrize("profile", PROFILES)
def test_the_seams_lifecycle_against_the_emulated_rig(profile, transport, tmp_path):
    cfg, cfg_file, key = rig_config(profile, transport, tmp_path)
    stop = threading.Event()
    with emulated_rig(cfg_file, key), profile_seam(cfg, stop) as hw:
        hw.configure(stop)  # returns once the peer answered
        assert not stop.is_set()
        judge = LockstepPacer(hw.ctx, hw.step, hw.why_silent)
        arm(hw)
        still = [period(hw, judge, (0.0, 0.0)) for _ in range(3)]
        assert {o.drive_mode for o in still} == {"enabled"}
        for o in still:  # a fresh observation of a still arm each period
            assert o.state_new and not o.state_stale and o.state_ns is not None
            assert np.all(np.isfinite(o.q)) and np.all(np.isfinite(o.dq))
        stamps = [o.state_ns for o in still]
        assert stamps == sorted(set(stamps)), stamps
        assert still[-1].q == pytest.approx(cfg.scenario.q0, abs=1e-3)
        assert np.abs(still[-1].dq).max() < 1e-3
        pushed = [period(hw, judge, PUSH) for _ in range(8)]
        last = pushed[-1]
        assert last.dq[0] > 1e-3 and last.dq[1] > 1e-3, last.dq  # the way the torque pushes
        assert last.q[0] > still[-1].q[0]
        braked = [period(hw, judge, (-PUSH[0], -PUSH[1])) for _ in range(8)]
        assert braked[-1].dq[0] < last.dq[0] and braked[-1].dq[1] < last.dq[1]
        assert all(o.state_new and o.drive_mode == "enabled" for o in pushed + braked)
        hw.deactivate()  # at once: the peer is still in the period the last write answered
        assert peer_after_deactivate(hw) == (False, False)
        hw.deactivate()  # safe twice


@pytest.mark.parametrize("profile", PROFILES)
def test_configure_without_a_peer_is_one_clear_error(profile, transport, tmp_path, monkeypatch):
    """No emulated hardware on the bus (a zenoh hub is there, so it is the hardware that is
    missing): ``configure`` raises one line from the package's exception tree, naming what
    did not answer."""
    cfg, _, _ = rig_config(profile, transport, tmp_path)
    monkeypatch.setattr(dsp_profile, "STARTUP_TIMEOUT_S", NO_PEER_TIMEOUT_S)
    stop = threading.Event()
    hub = open_session(cfg, listen=True)
    try:
        with profile_seam(cfg, stop) as hw:
            if isinstance(hw, Cia402Hardware):
                hw.master.settings = dataclasses.replace(
                    hw.master.settings, boot_timeout_s=NO_PEER_TIMEOUT_S
                )
            with pytest.raises((ControllerError, HalError)) as info:
                hw.configure(stop)
    finally:
        hub.close()
    message = str(info.value)
    assert "\n" not in message
    expected = "no boot-up" if profile == "cia402" else "no joint state (CAN)"
    assert expected in message, message
    if profile == "dsp":  # where it listened and what should be sending there
        assert f"nothing came on CAN {cfg.transport.can}: is a DSP sending there" in message
