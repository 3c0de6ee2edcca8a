"""The cia402 profile's start-up says once, after about 2 s without the drives' boot-up,
which drives it waits for on which bus and for how long at most (``RunContext.say``, on
stderr in the daemon); a boot whose drives answer at once says nothing."""

from __future__ import annotations

import threading

import can
import pytest

from hal.bus import isolated_spec
from hal.cia402_master.master import Cia402Master
from hal.config import RigConfig
from hal.errors import HalStopped
from rt_controller.runtime.cadence import MonotonicClock
from rt_controller.runtime.cia402_hardware import Cia402Hardware
from rt_controller.runtime.context import RunContext
from rt_controller.runtime.counters import RunCounters
from tests.controller.test_cia402_profile import Features
from tests.support.cia402 import drives_on_virtual_bus

CFG = RigConfig().with_overrides({"hardware.profile": "cia402"})
GIVE_UP_S = 10.0
"""The test stops a boot that said nothing by then (the product's boot timeout is 20 s)."""


def test_silent_drives_are_named_while_the_boot_waits():
    spec = isolated_spec("virtual")
    cfg = CFG.with_overrides({"transport.can": spec})
    stop, lines = threading.Event(), []

    def say(line: str) -> None:
        lines.append(line)
        stop.set()  # seen: no need to wait for the boot timeout

    bus = can.Bus(interface="virtual", channel=spec.partition(":")[2])
    master = Cia402Master.from_config(cfg, bus)
    ctx = RunContext(cfg, MonotonicClock(), stop, RunCounters(), None, say=say)
    guard = threading.Timer(GIVE_UP_S, stop.set)
    guard.start()
    try:
        with pytest.raises(HalStopped):
            Cia402Hardware(ctx, master, Features(), lockstep=True).configure(stop)
    finally:
        guard.cancel()
        master.close()
    ids = ", ".join(str(n.id) for n in master.nodes)
    assert lines == [f"waiting for the drives' boot-up on CAN {spec} (node ids {ids}, up to 20 s)"]


def test_drives_that_boot_at_once_are_not_announced():
    lines: list[str] = []
    with drives_on_virtual_bus(CFG) as bench:
        bus = can.Bus(interface="virtual", channel=bench.master.bus.channel_id)
        master = Cia402Master.from_config(CFG, bus)
        ctx = RunContext(
            CFG, MonotonicClock(), threading.Event(), RunCounters(), None, say=lines.append
        )
        hw = Cia402Hardware(ctx, master, Features(), lockstep=True)
        try:
            hw.configure(ctx.stop)
        finally:
            hw.deactivate()
            master.close()
    assert lines == []
