"""The cia402 hardware profile (rt_controller.runtime.cia402_hardware) through the seam's
lifecycle, lockstep, against the emulated drives on a virtual bus: configure boots them,
activate walks them to operation enabled, step/read/write run periods with torque, an EMCY
is a counted drive fault and the law stops, deactivate leaves them disabled."""

from __future__ import annotations

import math
import threading
from types import SimpleNamespace

import can
import numpy as np
import pytest

from hal.cia402_master.master import Cia402Master
from hal.config import RigConfig
from rt_controller.runtime.cadence import MonotonicClock
from rt_controller.runtime.cia402_hardware import Cia402Hardware
from rt_controller.runtime.context import RunContext
from rt_controller.runtime.counters import RunCounters
from tests.support.cia402 import drives_on_virtual_bus

CFG = RigConfig().with_overrides({"hardware.profile": "cia402"})
PERIOD_S = 1.0 / CFG.rates.control_hz


class Features:
    """The zenoh half, standing still: features f0, always fresh (this test is about CAN)."""

    def __init__(self) -> None:
        self.features = SimpleNamespace(latest=SimpleNamespace(f=CFG.scenario.f0))
        self.attached = False

    def attach(self) -> None:
        self.attached = True

    def detach(self) -> None:
        self.attached = False

    def as_dict(self) -> dict[str, int]:
        return {}

    def settle_images(self, timeout_s: float) -> bool:
        return True

    def poll(self, now_ns: int) -> None:
        pass

    def wait_pose(self, seq: int, timeout_s: float) -> bool:
        return True

    def latest(self, now_ns, judge):
        return np.array(CFG.scenario.f0), 0.0, False, True


class Judge:
    state_limit_s = 1.0
    status_limit_s = None

    def feature_age_ms(self, feat, recv_ns, wake_ns):
        return 0.0


@pytest.fixture(params=[True])
def profile(request):
    with drives_on_virtual_bus(CFG) as bench:
        bus = can.Bus(interface="virtual", channel=bench.master.bus.channel_id)
        master = Cia402Master.from_config(CFG, bus)
        ctx = RunContext(CFG, MonotonicClock(), threading.Event(), RunCounters(), None)
        hw = Cia402Hardware(ctx, master, Features(), lockstep=request.param)
        try:
            yield hw, bench
        finally:
            hw.deactivate()
            master.close()


def arm(hw: Cia402Hardware) -> int:
    for n in range(1, 20):
        if hw.activate(hw.ctx.clock.now_ns()):
            return n
    raise AssertionError("not armed")


def test_the_lifecycle_runs_periods_with_torque(profile):
    hw, bench = profile
    hw.configure(hw.ctx.stop)
    assert hw.features.attached
    assert arm(hw) <= 6
    k = hw.step(5.0)
    obs = hw.read(hw.ctx.clock.now_ns(), Judge())
    assert obs.drive_mode == "enabled" and obs.state_new and not obs.state_stale
    assert obs.q == pytest.approx(CFG.scenario.q0, abs=1e-5)
    hw.write((3.0, 0.4), sync=k, release_ns=0)
    k2 = hw.step(5.0)
    assert k2 == k + 1
    assert bench.rig.torques() == pytest.approx((3.0, 0.4))
    hw.write((3.0, 0.4), sync=k2, release_ns=0)
    hw.step(5.0)
    obs = hw.read(hw.ctx.clock.now_ns(), Judge())
    assert obs.dq[0] > 0 and obs.dq[1] > 0
    diag = hw.diagnostics()
    assert diag["dsp"]["torque_enabled"] and diag["dsp"]["profile"] == "cia402"
    assert diag["dsp"]["sync_to_tpdo_us_median"] > 0
    hw.deactivate()
    assert [s[0] for s in hw.deactivation] == ["quick stop", "disable operation", "pre-operational"]
    assert bench.rig.torques() == (0.0, 0.0)


def test_a_drive_fault_is_counted_and_holds_the_drives_off(profile):
    hw, bench = profile
    hw.configure(hw.ctx.stop)
    arm(hw)
    k = hw.step(5.0)
    bench.rig.poll(bench.clock.t + 3 * PERIOD_S)  # SYNC loss: FAULT + EMCY 0x8700
    for _ in range(5):
        hw.write((1.0, 0.1), sync=k, release_ns=0)
        k = hw.step(5.0)
        obs = hw.read(hw.ctx.clock.now_ns(), Judge())
        if sum(hw.ctx.counters.dsp_faults.values()) == 2:
            break
    assert obs.drive_mode == "fault"
    assert dict(hw.ctx.counters.dsp_faults) == {"emcy_8700": 2}
    assert hw.ctx.counters.drive_ticks["fault"] >= 1
    # no automatic fault reset: the drives stay in FAULT, torque off
    for _ in range(3):
        hw.write((1.0, 0.1), sync=k, release_ns=0)
        k = hw.step(5.0)
    assert [d.power.state.name for d in bench.rig.drives] == ["FAULT", "FAULT"]
    assert bench.rig.torques() == (0.0, 0.0)
    # the operator arms again: the walk resets the fault (a rising edge of bit 7)
    assert hw.command("arm") is None
    for _ in range(8):
        hw.write((0.0, 0.0), sync=k, release_ns=0)
        k = hw.step(5.0)
    assert hw.read(hw.ctx.clock.now_ns(), Judge()).drive_mode == "enabled"
    assert not math.isnan(hw.read(hw.ctx.clock.now_ns(), Judge()).q[0])


def test_the_profile_key_is_validated_and_overridden_by_the_command_line():
    from hal.errors import HalConfigError
    from rt_controller.config_rules import apply_overrides

    assert RigConfig().hardware.profile == "dsp"
    assert apply_overrides(RigConfig(), profile="cia402").hardware.profile == "cia402"
    with pytest.raises(HalConfigError, match=r"hardware.profile: must be dsp or cia402, not 'x'"):
        RigConfig().with_overrides({"hardware.profile": "x"})


@pytest.mark.parametrize("profile", [False], indirect=True)
def test_realtime_latches_each_torque_with_its_own_sync(profile):
    """Realtime: arming sends one SYNC per call (counted), the tick's RPDO goes out with the
    SYNC that latches it, and the state's age since its SYNC stands for the CST delay."""
    hw, bench = profile
    hw.configure(hw.ctx.stop)
    calls = 1
    while not hw.activate(hw.ctx.clock.now_ns()):
        assert hw.master.wait_tpdos(hw.master.sync_count, 5.0)  # a period: the drives answer
        calls += 1
        assert calls < 20, "not armed"
    assert hw.ctx.counters.arming_ticks == calls - 1 >= 3
    syncs = bench.rig.syncs
    hw.write((2.0, 0.3), sync=None, release_ns=hw.ctx.clock.now_ns())
    assert hw.master.wait_tpdos(hw.master.sync_count, 5.0)
    assert bench.rig.syncs == syncs + 1  # the SYNC went with the RPDO
    assert bench.rig.torques() == pytest.approx((2.0, 0.3))
    obs = hw.read(hw.ctx.clock.now_ns(), Judge())
    assert obs.actuation_delay_ms == 0.0 and obs.state_age_ms > 0
    assert obs.drive_mode == "enabled"
