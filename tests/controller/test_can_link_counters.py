"""What the CAN link counted besides the frames' verdicts (a receive stamp not on the wall
clock, a driver error, a drain cut short) is in the controller's ``/diagnostics`` ``can_rx``
block when it happened, so ``hil info`` and ``hil up`` show it; a run without any adds no
key."""

from __future__ import annotations

import threading

from hal.config import RigConfig
from hal.joint_client import JointClient
from hal.secoc import rig_key
from hal.vision_receivers import FeatureDecoder
from rt_controller.runtime.context import RunContext
from rt_controller.runtime.counters import RunCounters
from rt_controller.runtime.feature_link import FeatureLink
from rt_controller.runtime.hardware import DspHardware
from tests.hal.test_foreign_can_stamps import StampedBus, _state_frames
from tests.support.fake_clock import FakeClock


class NoSession:
    def subscribe(self, key: str, on_payload: object) -> object:
        class Subscriber:
            def undeclare(self) -> None:
                pass

        return Subscriber()


class NoRecorder:
    dropped = 0


def _can_rx(stamp: float) -> dict:
    cfg = RigConfig()
    key = rig_key(cfg)
    stopped = threading.Event()
    stopped.set()  # configure returns at once
    ctx = RunContext(cfg, FakeClock(1_000_000_000), stopped, RunCounters(), NoRecorder())
    dsp = JointClient(StampedBus(_state_frames(stamp, key)), cfg, key=key, owns_bus=True)
    decoder = FeatureDecoder.from_config(cfg.controller, key=key)
    link = FeatureLink(ctx, NoSession(), decoder, by_callback=True, record_raw=False)
    hw = DspHardware(ctx, dsp, link, lockstep=True, record_raw=False)
    hw.configure(stopped)
    dsp.drain()
    can_rx = hw.diagnostics()["can_rx"]
    dsp.close()
    return can_rx


def test_foreign_stamps_are_in_the_can_rx_block() -> None:
    can_rx = _can_rx(5_000.0)  # stamped from boot
    assert can_rx["foreign_stamps"] == 2 and can_rx["accepted"] == 2
    assert "transport_errors" not in can_rx and "drains_cut" not in can_rx


def test_a_run_without_them_adds_no_key() -> None:
    assert "foreign_stamps" not in _can_rx(0.0)  # unstamped: judged on arrival
