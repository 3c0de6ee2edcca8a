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
import os
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hal.bus import open_bus
from hal.cia402_master.master import Cia402Master
from hal.config import RigConfig
from hal.errors import HalStopped
from hal.hardware_interface import HardwareInterface
from hal.joint_client import JointClient
from hal.secoc import rig_key
from hal.signals import signal_name_of
from hal.vision_receivers import FeatureDecoder
from hal.zenoh_session import ZenohSession, open_session
from rt_controller.calibration.link import ParameterServer
from rt_controller.calibration.parameters import ParameterService
from rt_controller.control.controller import Controller
from rt_controller.runtime import diagnostics
from rt_controller.runtime.cadence import Clock, MonotonicClock
from rt_controller.runtime.cia402_hardware import Cia402Hardware
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
from rt_controller.runtime.pacers import LockstepPacer, Pacer, RealtimePacer
from rt_controller.runtime.realtime import GcPaused, apply_realtime
from rt_controller.runtime.recorder_process import RecorderProcess


@dataclass
class DaemonOptions:
    """How one daemon run is wired (the transports and the clock mode are configuration:
    ``transport.*``, ``controller.clock``)."""

    duration_s: float = 0.0
    """0 = until stopped (realtime) or until the Sync frames stop (lockstep)."""
    log_path: Path | None = None
    replace_log: bool = True
    """Replace an existing ``log_path`` (False: refuse it, created with ``O_EXCL``)."""
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
    images_owed_before: tuple[int, ...] = ()
    """A plan's run after the first: the camera images the run before was still owed
    (:meth:`~rt_controller.runtime.feature_link.FeatureLink.images_owed`), kept out of this
    run's log should they come late."""


CanLink = JointClient | Cia402Master
"""The CAN side of a run, by ``hardware.profile``."""


@contextlib.contextmanager
def open_links(cfg: RigConfig, stop: threading.Event) -> Iterator[tuple[CanLink, ZenohSession]]:
    """The controller's links on ``cfg.transport`` (:func:`open_can`, then the zenoh session),
    both closed at the end. :class:`HalStopped` when ``stop`` is set while waiting for zenoh."""
    with contextlib.ExitStack() as links:
        can = links.enter_context(open_can(cfg))
        session = open_zenoh(cfg, stop)
        links.callback(session.close)
        yield can, session


def open_zenoh(cfg: RigConfig, stop: threading.Event) -> ZenohSession:
    """The controller's zenoh session, waiting for the hub; :class:`HalStopped` on ``stop``."""
    return open_session(cfg, listen=False, wait_s=STARTUP_TIMEOUT_S, stop_event=stop)


@contextlib.contextmanager
def open_can(cfg: RigConfig) -> Iterator[CanLink]:
    """The CAN side of ``hardware.profile``: the DSP's client in poll mode (the control thread
    reads the bus itself, no receive thread) or the ``cia402`` profile's CANopen master (whose
    receive thread is canopen's); closed at the end. Opened first: a bad ``transport.can`` is
    reported at once, before a log is made or zenoh is waited for."""
    if cfg.hardware.profile == "cia402":
        master = Cia402Master.from_config(
            cfg, open_bus(cfg.transport.can, bitrate=cfg.cia402.bitrate, fd=False)
        )
        try:
            yield master
        finally:
            master.close()
    else:
        with JointClient.open(None, cfg) as client:
            yield client


def build_hardware(
    ctx: RunContext,
    can: CanLink,
    session: Any,
    features: FeatureDecoder,
    *,
    record_raw: bool,
    images_owed_before: tuple[int, ...] = (),
) -> DspHardware | Cia402Hardware:
    """The run's hardware profile on its open links (the profile of the ``can`` link given),
    with the features of ``session`` decoded by ``features``."""
    lockstep = ctx.cfg.controller.clock == "lockstep"
    link = FeatureLink(
        ctx, session, features, by_callback=lockstep, record_raw=record_raw,
        owed_before=images_owed_before,
    )  # fmt: skip
    if isinstance(can, Cia402Master):
        return Cia402Hardware(ctx, can, link, lockstep=lockstep, record_raw=record_raw)
    return DspHardware(ctx, can, link, lockstep=lockstep, record_raw=record_raw)


def claim_log(folder: Path, stem: str) -> Path:
    """A new log ``folder/stem.mcap`` (``stem-2.mcap``, ... when taken), created empty at once
    (``O_EXCL``): two controllers started in the same second never write one file."""
    folder.mkdir(parents=True, exist_ok=True)
    path, n = folder / f"{stem}.mcap", 1
    while True:
        try:
            os.close(os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644))
            return path
        except FileExistsError:
            n += 1
            path = folder / f"{stem}-{n}.mcap"


class ControllerDaemon:
    """One run: the law, the recorder, the links, the loop; :meth:`run` gives the summary."""

    def __init__(self, cfg: RigConfig, options: DaemonOptions, stop: threading.Event) -> None:
        self.cfg = cfg
        self.opts = options
        self.stop = stop
        self.lockstep = cfg.controller.clock == "lockstep"
        """The world's steps pace the run (``controller.clock``), not the monotonic clock."""
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
        d = options.duration_s
        self.counters.planned_ticks = math.floor(d * cfg.rates.control_hz + 1e-9) if d > 0 else None
        self.params = ParameterService(cfg)
        """Online parameter changes: any thread submits, the loop takes them at a tick
        boundary (:mod:`rt_controller.calibration.parameters`)."""
        stem = f"run-{time.strftime('%Y%m%d-%H%M%S')}-{cfg.controller.law}"
        self.log_path = options.log_path or claim_log(Path(cfg.controller.log_dir), stem)
        self._final_diagnostics: dict[str, Any] | None = None
        self.images_owed: tuple[int, ...] = ()
        """After :meth:`run`: the camera images announced that did not come (the next run of a
        plan is given them: ``DaemonOptions.images_owed_before``)."""

    def what_runs(self, cfg: RigConfig | None = None) -> dict[str, Any]:
        """What this run is: clock, rate, duration, law (with the horizon for rhc), CAN bus;
        of ``cfg`` (default: the configuration the run starts with)."""
        cfg = cfg or self.cfg
        rhc = cfg.controller.law == "rhc"
        return {
            "clock": cfg.controller.clock,
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
            "clock": cfg.controller.clock,
            "can": transport.can,
            "zenoh": transport.zenoh_config or transport.zenoh_endpoint,
            "recorder": "process (spawn)",
        }
        return RecorderProcess(
            self.log_path,
            cfg,
            run_info=run_info,
            scene=self.opts.scene,
            live=self.opts.live,
            backpressure=self.lockstep,  # no deadline: wait for a busy recorder
            replace=self.opts.replace_log or self.opts.log_path is None,  # claim_log made it
            stop=self.stop,
        )

    def run(self, links: tuple[CanLink, Any] | None = None) -> dict[str, Any]:
        """Open the CAN link, the recorder and the zenoh session, run until stopped; the
        summary. ``links``: a CAN link and zenoh session that outlive the run (``hil controller
        --plan``, tests), left as found. A CAN link that cannot open makes no log; from the
        recorder on, the log says how the run ended. The links close before the recorder."""
        own = contextlib.ExitStack()
        try:
            can = links[0] if links else own.enter_context(open_can(self.cfg))
            rec = self._open_recorder()
        except BaseException:
            own.close()
            self._give_back_log()
            raise
        try:
            with own:
                session = links[1] if links else open_zenoh(self.cfg, self.stop)
                if not links:
                    own.callback(session.close)
                self._run_with(can, session, rec)
        except HalStopped:  # told to stop while waiting for zenoh
            self.counters.stopped_before_arming = True
            self.counters.end_reason = "stopped"
        except Exception as exc:  # the log says why the run ended, as the error does
            if self._final_diagnostics is None:
                self.counters.end_reason = f"failed to start: {exc}"
            raise
        finally:
            if self._final_diagnostics is None:  # no loop: no hardware counters
                self._record_end(rec, self._bare_diagnostics(rec))
            rec.close()
        return self._summary(rec)

    def _give_back_log(self) -> None:
        """The default log's name, claimed at start (:func:`claim_log`), given back when no
        recorder wrote into it: a run that never started leaves no empty file."""
        if self.opts.log_path is None:
            with contextlib.suppress(OSError):
                if self.log_path.stat().st_size == 0:
                    self.log_path.unlink()

    def _bare_diagnostics(self, rec: RecorderProcess) -> dict[str, Any]:
        """The final ``/diagnostics`` record of a run stopped before its hardware existed."""
        return diagnostics.build(
            t_ns=self.clock.now_ns(), tick=self.counters.ticks, can_rx={}, features={}, dsp={},
            controller=self.counters.controller_block(), recorder=rec.as_dict(), final=True,
        )  # fmt: skip

    def _record_end(self, rec: Any, record: dict[str, Any]) -> None:
        """Write the run's final ``/diagnostics`` record, with how the run ended, on every
        orderly end (a stop before the first tick included): without it, ``hil info`` takes
        the log for one of a killed run."""
        self._final_diagnostics = diagnostics.with_run_end(
            record, self.counters.planned_ticks, self.counters.end_reason, self.counters.judged(),
            stop_signal=signal_name_of(self.stop),
        )  # fmt: skip
        rec.record_diagnostics(self._final_diagnostics, final=True)

    def _run_with(self, can: CanLink, session: Any, rec: RecorderProcess) -> None:
        """The run on open links (:func:`open_links`): the parts, the live stream, the loop."""
        cfg = self.cfg
        ctx = RunContext(cfg, self.clock, self.stop, self.counters, rec, say=self._say)
        hw = build_hardware(
            ctx, can, session, self.features, record_raw=self.opts.record_raw,
            images_owed_before=self.opts.images_owed_before,
        )  # fmt: skip
        pacer: Pacer = (
            LockstepPacer(ctx, hw.step, hw.why_silent)
            if self.lockstep
            else RealtimePacer(ctx, hw.wait_inputs)
        )
        loop = ControlLoop(ctx, self.controller, hw, pacer, self.params)
        tuning = ParameterServer(self.params, rig_key(cfg)).attach(session)  # `hil param`
        try:
            self._start_and_loop(hw, loop)
        finally:
            tuning.undeclare()
            hw.deactivate()
            self.images_owed = hw.features.images_owed()

    @staticmethod
    def _say(line: str) -> None:
        """The run's word to the operator, on stderr (e.g. a slow start-up's wait)."""
        print(f"hil controller: {line}", file=sys.stderr, flush=True)

    def _start_and_loop(self, hw: HardwareInterface, loop: ControlLoop) -> None:
        """Warm up, configure the hardware (the peer answers), lock memory, then the loop
        (which activates it); deactivated at the end."""
        cfg = self.cfg
        self.controller.warm_up()  # every branch of the tick, before the DSP is armed
        hw.configure(self.stop)
        if self.stop.is_set():
            self.counters.stopped_before_arming = True
            self.counters.end_reason = "stopped"
            self._record_end(loop.ctx.recorder, loop.diagnostics(final=True))
            return  # told to stop during start-up: the DSP is never armed
        if self.opts.realtime_settings:
            # After warm-up and the first inputs: the pages locked are those the tick, the
            # receive paths and the recorder have touched (runtime/realtime.py).
            rt = apply_realtime(cfg.controller.rt_priority, cfg.controller.cpu)
            for w in rt.warnings:
                print(f"hil controller: warning: {w}", file=sys.stderr)
        before = None if self.lockstep else cpu_ticks()
        try:
            with GcPaused():
                loop.run(self.counters.planned_ticks)
        except Exception as exc:  # not "duration": the final record says it failed
            self.counters.end_reason = f"failed: {exc}"
            raise
        finally:
            self.counters.host_steal_percent = steal_percent(before, cpu_ticks())
            self.counters.spin_s = self.clock.spun_ns / 1e9
            if self.stop.is_set() and self.counters.end_reason == "duration":
                self.counters.end_reason = "stopped"
            hw.deactivate()
            self._record_end(loop.ctx.recorder, loop.diagnostics(final=True))

    def _summary(self, rec: RecorderProcess) -> dict[str, Any]:
        # the law in force at the end, with its settings (a live switch may have changed them)
        out = {**self.what_runs(self.controller.cfg), **self.counters.as_dict()}
        out.update(log=str(self.log_path), recorder=rec.as_dict())
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
        out["parameters"] = diagnostics.values_of(final, "parameters")
        if (by := signal_name_of(self.stop)) is not None:
            out["stop_signal"] = by  # which signal the "stopped" end_reason was
        out["problems"] = run_problems(out)
        out["warnings"] = run_warnings(out)
        return out


__all__ = [
    "ControllerDaemon",
    "DaemonOptions",
    "build_hardware",
    "claim_log",
    "open_links",
    "run_problems",
]
