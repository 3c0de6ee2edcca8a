"""The controller daemon: wires one run's parts together and reports on it.

The parts: the recorder (its own process), the links (CAN client, zenoh session), the
hardware profile over them (:class:`~rt_controller.runtime.hardware.DspHardware`, the seam's
lifecycle: configure → activate → read/write → deactivate), the pacer of the clock mode and
the control loop (:mod:`rt_controller.runtime.loop`: read → decide → write → record), all
sharing one :class:`~rt_controller.runtime.context.RunContext`. Safety lives in the
per-tick rule: stale features put the loop in *hold* (tau = -2 R dq, a pure joint damper) and
the law is re-initialised when they return; a silent DSP gets zero torque.
"""

from __future__ import annotations

import contextlib
import math
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hal.cia402_master.master import Cia402Master
from hal.config import RigConfig
from hal.errors import HalStopped
from hal.hardware_interface import HardwareInterface
from hal.joint_client import JointClient
from hal.secoc import rig_key
from hal.vision_receivers import FeatureDecoder
from hal.zenoh_session import ZenohSession, open_session
from rt_controller.calibration.link import ParameterServer
from rt_controller.calibration.parameters import ParameterService
from rt_controller.control.controller import Controller
from rt_controller.runtime import diagnostics
from rt_controller.runtime.cadence import Clock, MonotonicClock
from rt_controller.runtime.cia402_hardware import Cia402Hardware, open_cia402_links
from rt_controller.runtime.context import RunContext
from rt_controller.runtime.counters import (
    OutageTracker,
    RunCounters,
    run_problems,
    run_warnings,
)
from rt_controller.runtime.feature_link import FeatureLink
from rt_controller.runtime.hardware import STARTUP_TIMEOUT_S, DspHardware
from rt_controller.runtime.host_steal import cpu_ticks, steal_percent
from rt_controller.runtime.loop import ControlLoop
from rt_controller.runtime.pacers import ClockMode, LockstepPacer, Pacer, RealtimePacer
from rt_controller.runtime.realtime import GcPaused, apply_realtime
from rt_controller.runtime.recorder_process import RecorderProcess


@dataclass
class DaemonOptions:
    """How one daemon run is wired (the transports and the clock mode are configuration:
    ``transport.*``, ``controller.clock``)."""

    duration_s: float = 0.0
    """0 = until stopped (realtime) or until the Sync frames stop (lockstep)."""
    log_path: Path | None = None
    realtime_settings: bool = True
    record_raw: bool = True
    """Also record every CAN frame and vision payload as received."""
    live: bool = True
    """Publish every cycle and diagnostics record on zenoh (``hil/controller/cycle``,
    ``hil/controller/diagnostics``) from the recorder, for ``hil monitor``."""
    scene: bool = True
    """Draw the arm into the MCAP (Foxglove scene topics, :mod:`rt_controller.monitor.scene`)."""
    clock: Clock | None = None
    """The loop's clock (default: the monotonic clock, sleeping then spinning
    ``controller.spin_us`` before each release); tests pass a fake one."""


@contextlib.contextmanager
def open_links(cfg: RigConfig, stop: threading.Event) -> Iterator[tuple[JointClient, ZenohSession]]:
    """The controller's links: the CAN client in poll mode (the control thread reads the bus
    itself, no receive thread) and the zenoh session, both on ``cfg.transport``. The bus
    first: a bad ``transport.can`` is
    reported at once, not after waiting for zenoh. :class:`HalStopped` when ``stop`` is set
    while waiting for zenoh."""
    with JointClient.open(None, cfg) as dsp:
        session = open_session(cfg, listen=False, wait_s=STARTUP_TIMEOUT_S, stop_event=stop)
        try:
            yield dsp, session
        finally:
            session.close()


class ControllerDaemon:
    """One run: the law, the recorder, the links, the loop; :meth:`run` gives the summary."""

    def __init__(self, cfg: RigConfig, options: DaemonOptions, stop: threading.Event) -> None:
        self.cfg = cfg
        self.opts = options
        self.stop = stop
        self.mode = ClockMode(cfg.controller.clock)
        self.clock: Clock = options.clock or MonotonicClock(
            spin_ns=round(cfg.controller.spin_us * 1e3)
        )
        self.controller = Controller(cfg)
        """The run's controller (its ``decide`` is the per-tick rule)."""
        self.features = FeatureDecoder.from_config(cfg.controller, key=rig_key(cfg))
        """The decoder every feature message of the run goes through."""
        self.counters = RunCounters(
            outages=OutageTracker.from_config(cfg.controller), period_s=1 / cfg.rates.control_hz
        )
        self.params = ParameterService(cfg)
        """Online parameter changes: any thread submits, the loop takes them at a tick
        boundary (:mod:`rt_controller.calibration.parameters`)."""
        stamp = time.strftime("%Y%m%d-%H%M%S")
        default_log = Path(cfg.controller.log_dir) / f"run-{stamp}-{cfg.controller.law}.mcap"
        self.log_path = options.log_path or default_log
        self.loop: ControlLoop | None = None
        self._final_diagnostics: dict[str, Any] | None = None

    def what_runs(self) -> dict[str, Any]:
        """What this run is: clock, rate, duration, law (with the horizon for rhc), CAN bus."""
        cfg = self.cfg
        rhc = cfg.controller.law == "rhc"
        return {
            "clock": self.mode.value,
            "rate_hz": cfg.rates.control_hz,
            "duration_s": self.opts.duration_s or None,
            "law": cfg.controller.law,
            "horizon_s": cfg.rhc.horizon if rhc else None,
            "steps": cfg.rhc.steps if rhc else None,
            "can": cfg.transport.can,
        }

    # --- wiring -----------------------------------------------------------------------------
    def _open_recorder(self) -> RecorderProcess:
        """This run's log, written by a recorder process of its own (which also publishes the
        live stream on ``cfg.transport``)."""
        cfg, transport = self.cfg, self.cfg.transport
        run_info = {
            "clock": self.mode.value,
            "can": transport.can,
            "zenoh": transport.zenoh_config or transport.zenoh_endpoint,
            "recorder": "process (spawn)",
        }
        paced_by_sync = self.mode is ClockMode.LOCKSTEP  # no deadline: wait for a busy recorder
        return RecorderProcess(
            self.log_path,
            cfg,
            run_info=run_info,
            scene=self.opts.scene,
            live=self.opts.live,
            backpressure=paced_by_sync,
        )

    def run(self) -> dict[str, Any]:
        """Open the recorder and the links, run until stopped; the summary. The recorder is
        finished on every exit."""
        rec = self._open_recorder()
        try:
            if self.cfg.hardware.profile == "cia402":
                with open_cia402_links(self.cfg, self.stop) as (master, session):
                    self._run_with(None, session, rec, master=master)
            else:
                with open_links(self.cfg, self.stop) as (dsp, session):
                    self._run_with(dsp, session, rec)
        except HalStopped:  # told to stop while waiting for zenoh
            self.counters.stopped_before_arming = True
        finally:
            rec.close()
        return self._summary(rec)

    def run_on(self, dsp: JointClient, session: Any) -> dict[str, Any]:
        """One run on links that outlive it (``hil controller --plan``, tests: a poll-mode
        client, an open session); the summary. Leaves them as it found them."""
        rec = self._open_recorder()
        try:
            self._run_with(dsp, session, rec)
        finally:
            rec.close()
        return self._summary(rec)

    def _run_with(
        self,
        dsp: JointClient | None,
        session: Any,
        rec: RecorderProcess,
        *,
        master: Cia402Master | None = None,
    ) -> None:
        """The run on open links (the DSP's client, or the cia402 profile's CANopen
        ``master``): the parts, the live stream, the loop."""
        cfg, opts = self.cfg, self.opts
        ctx = RunContext(cfg, self.clock, self.stop, self.counters, rec)
        lockstep = self.mode is ClockMode.LOCKSTEP
        hw: HardwareInterface
        if master is not None:
            link = FeatureLink(
                ctx, session, self.features, by_callback=lockstep, record_raw=opts.record_raw
            )
            hw = Cia402Hardware(ctx, master, link, lockstep=lockstep, record_raw=opts.record_raw)
        else:
            assert dsp is not None
            hw = DspHardware(
                ctx, dsp, session, self.features, lockstep=lockstep, record_raw=opts.record_raw
            )
        pacer: Pacer = (
            LockstepPacer(ctx, hw.step) if lockstep else RealtimePacer(ctx, hw.wait_inputs)
        )
        loop = self.loop = ControlLoop(ctx, self.controller, hw, pacer, self.params)
        tuning = ParameterServer(self.params, rig_key(cfg)).attach(session)  # `hil param`
        try:
            self._start_and_loop(hw, loop)
        finally:
            tuning.undeclare()
            hw.deactivate()

    def _start_and_loop(self, hw: HardwareInterface, loop: ControlLoop) -> None:
        """Warm up, configure the hardware (the peer answers), lock memory, then the loop
        (which activates it); deactivated at the end."""
        cfg = self.cfg
        self.controller.warm_up()  # every branch of the tick, before the DSP is armed
        hw.configure(self.stop)
        if self.stop.is_set():
            self.counters.stopped_before_arming = True
            return  # told to stop during start-up: the DSP is never armed
        if self.opts.realtime_settings:
            # After warm-up and the first inputs: the pages locked are those the tick, the
            # receive paths and the recorder have touched (runtime/realtime.py).
            rt = apply_realtime(cfg.controller.rt_priority, cfg.controller.cpu)
            for w in rt.warnings:
                print(f"hil controller: warning: {w}", file=sys.stderr)
        d = self.opts.duration_s
        max_ticks = math.floor(d * cfg.rates.control_hz + 1e-9) if d > 0 else None
        self.counters.planned_ticks = max_ticks
        before = cpu_ticks() if self.mode is ClockMode.REALTIME else None
        try:
            with GcPaused():
                loop.run(max_ticks)
        finally:
            self.counters.host_steal_percent = steal_percent(before, cpu_ticks())
            self.counters.spin_s = self.clock.spun_ns / 1e9
            if self.stop.is_set() and self.counters.end_reason == "duration":
                self.counters.end_reason = "stopped"
            hw.deactivate()
            self._final_diagnostics = loop.diagnostics(final=True)
            loop.ctx.recorder.record_diagnostics(self._final_diagnostics, final=True)

    def _summary(self, rec: RecorderProcess) -> dict[str, Any]:
        rec.close()
        out = {**self.what_runs(), **self.counters.as_dict()}
        out.update(law=self.controller.law, log=str(self.log_path), recorder=rec.as_dict())
        if rec.error is not None:
            out["log_error"] = str(rec.error)
        final = self._final_diagnostics or {}
        out["rejections"] = {
            "can_rx": diagnostics.values_of(final, "can_rx"),
            "features": diagnostics.values_of(final, "features"),
            "dsp_rejected_frames": int(
                diagnostics.values_of(final, "dsp").get("rejected_frames", 0)
            ),
        }
        out["problems"] = run_problems(out)
        out["warnings"] = run_warnings(out)
        return out


__all__ = ["ControllerDaemon", "DaemonOptions", "open_links", "run_problems"]
