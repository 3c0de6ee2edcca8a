"""The EMCYs of a cia402 run, from the frames its log recorded: the profile (record_raw) with
a real recorder against the emulated drives on a virtual bus; a SYNC loss faults both drives
(EMCY 0x8700), the operator's arm resets them (EMCY error reset), and ``hil report``'s
CANopen section lists each with its node, code and time, as the log's ``/hal/canopen`` does."""

from __future__ import annotations

import threading

import can
from rich.console import Console

from hal.cia402_master.master import Cia402Master
from rt_controller.logtools.deadline_report import summarize
from rt_controller.logtools.reader import read_log
from rt_controller.logtools.report_text import render_text
from rt_controller.runtime.cadence import MonotonicClock
from rt_controller.runtime.cia402_hardware import Cia402Hardware
from rt_controller.runtime.context import RunContext
from rt_controller.runtime.counters import RunCounters
from rt_controller.runtime.recorder import CycleRecorder
from tests.controller.test_cia402_profile import CFG, PERIOD_S, Features, Judge, arm
from tests.support.cia402 import drives_on_virtual_bus


def run_until(hw: Cia402Hardware, k: int, tau: tuple[float, float], mode: str) -> int:
    """Lockstep periods with torque ``tau`` until the drives' mode is ``mode``; the last k."""
    for _ in range(10):
        hw.write(tau, sync=k, release_ns=0)
        k = hw.step(5.0)
        if hw.read(hw.ctx.clock.now_ns(), Judge()).drive_mode == mode:
            return k
    raise AssertionError(f"the drives did not reach {mode}")


def test_report_lists_the_emcys_of_a_sync_loss_and_of_the_reset(tmp_path):
    path = tmp_path / "emcy.mcap"
    nodes = {CFG.cia402.node_id_1, CFG.cia402.node_id_2}
    with drives_on_virtual_bus(CFG) as bench, CycleRecorder(path, CFG) as rec:
        bus = can.Bus(interface="virtual", channel=bench.master.bus.channel_id)
        master = Cia402Master.from_config(CFG, bus)
        ctx = RunContext(CFG, MonotonicClock(), threading.Event(), RunCounters(), rec)
        hw = Cia402Hardware(ctx, master, Features(), lockstep=True, record_raw=True)
        try:
            hw.configure(ctx.stop)
            arm(hw)
            k = hw.step(5.0)
            bench.rig.poll(bench.clock.t + 3 * PERIOD_S)  # SYNC loss: FAULT + EMCY 0x8700
            k = run_until(hw, k, (1.0, 0.1), "fault")
            assert hw.command("arm") is None  # the walk resets the fault: EMCY error reset
            run_until(hw, k, (0.0, 0.0), "enabled")
        finally:
            hw.deactivate()
            master.close()
    loaded = read_log(path)
    report = summarize(loaded)
    co = report["canopen"]
    decoded = [  # the recorder's /hal/canopen has them too, for Foxglove
        (r["node"], r["fields"]["code"], r["fields"]["register"])
        for r in loaded.canopen
        if r["kind"] == "emcy" and not r["fields"]["error_reset"]
    ]
    assert sorted((n, c) for n, c, _reg in decoded) == sorted((n, 0x8700) for n in nodes)
    assert all(reg for _n, _c, reg in decoded), decoded  # the error register is set
    faults = [(e["node"], e["code"]) for e in co["emcys"] if not e["error_reset"]]
    resets = [e["node"] for e in co["emcys"] if e["error_reset"]]
    assert sorted(faults) == sorted((n, "0x8700") for n in nodes), co["emcys"]
    assert sorted(resets) == sorted(nodes), co["emcys"]
    assert set(co["drive_states"]) == {str(n) for n in nodes}, co["drive_states"]
    for states in co["drive_states"].values():  # enabled, faulted, enabled again
        fault = states.index("FAULT")
        assert "OPERATION ENABLED" in states[:fault] and "OPERATION ENABLED" in states[fault:]
    console = Console(record=True, width=120)
    render_text(report, console)
    text = console.export_text()
    assert "EMCY" in text and "0x8700" in text and "error reset" in text
