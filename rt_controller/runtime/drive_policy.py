"""The controller's side of the DSP's drive state machine: follow every DspStatus, count
faults, re-arm by policy, and say in which mode each tick runs (the law runs only in
``enabled``)."""

from __future__ import annotations

from hal.drive_state import (
    MODE_ENABLED,
    MODE_NO_STATUS,
    DriveEvent,
    DriveMonitor,
    DriveUpdate,
    FaultReason,
)
from hal.joint_client import JointClient
from rt_controller.errors import ControllerError
from rt_controller.runtime.context import RunContext

ENABLE_TIMEOUT_S = 5.0
"""How long arming waits for the DSP to report *operation enabled* after ENABLE."""


class DrivePolicy:
    """Follows the DSP's drive state for one run and applies the re-arm policy.

    Policy (``controller.rearm_after_trip``, ``controller.rearm_after_restart``): a watchdog
    fault means this loop was late, so it may be reset and re-armed once per trip; a DSP that
    restarted (new session) or was disabled by someone else is re-armed only when configured;
    a limit or encoder fault never is.
    """

    def __init__(self, ctx: RunContext) -> None:
        self.ctx = ctx
        self.monitor = DriveMonitor()
        self.held_off = False
        """The operator disarmed the DSP: no policy re-arm until the operator arms it."""

    def operate(self, dsp: JointClient, action: str) -> str | None:
        """Do an operator's ``arm``, ``disarm`` or ``mark`` (nothing to do); None when done,
        else why not."""
        if action == "disarm":
            if self.held_off:
                return "already disarmed by the operator"
            self.held_off = True
            dsp.disable()
        elif action == "arm":
            if not self.held_off and self.monitor.mode == MODE_ENABLED:
                return "already armed"
            self.held_off = False
            dsp.enable(reset_fault=True)
        return None

    @property
    def mode(self) -> str:
        """The drive mode as last followed (:data:`hal.drive_state.MODES`)."""
        return self.monitor.mode

    def enabled_now(self, dsp: JointClient, expired: bool) -> bool:
        """During arming: whether the DSP reports *operation enabled* (its statuses are
        followed, not acted on: ENABLE resets); raises once ``expired`` and it does not."""
        status = dsp.status
        for st in dsp.take_statuses():
            self.monitor.update(st)
        if self.monitor.mode == MODE_ENABLED:
            return True
        if expired:
            state = "no DspStatus" if status is None else status.drive_state.label
            fault = "" if status is None else f", fault {status.fault_reason.label}"
            raise ControllerError(
                f"the DSP did not enter operation enabled within {ENABLE_TIMEOUT_S:g} s "
                f"(state {state}{fault})"
            )
        return False

    def follow(self, dsp: JointClient, now_ns: int, status_limit_s: float | None) -> str:
        """Feed every status since the last read to the monitor, in order, acting on each
        update's events (a fault, reset and enable that arrived between two reads are all
        seen); the drive mode of this tick. A status older than ``status_limit_s`` means a
        silent DSP (None: no limit, the pacer's clock already proves the DSP alive)."""
        for status in dsp.take_statuses():
            self._on_events(dsp, self.monitor.update(status))
        mode = self.monitor.mode
        if status_limit_s is not None:
            age = dsp.status_age_s_at(now_ns)
            if age is None or age > status_limit_s:
                mode = MODE_NO_STATUS  # a silent DSP: its last word no longer counts
        if mode != MODE_ENABLED:
            self.ctx.counters.drive_ticks[mode] += 1
        return mode

    def _on_events(self, dsp: JointClient, upd: DriveUpdate) -> None:
        ctl, n = self.ctx.cfg.controller, self.ctx.counters
        for ev in upd.events:
            if ev is DriveEvent.FAULT:
                n.dsp_faults[upd.fault.label] += 1
            if self.held_off:  # the operator's disarm stands: count, never re-arm
                continue
            if ev is DriveEvent.FAULT and upd.fault is FaultReason.WATCHDOG:
                n.watchdog_trips += 1
                if ctl.rearm_after_trip:
                    dsp.enable(reset_fault=True)
                    n.rearms += 1
            elif ev in (DriveEvent.DSP_RESTARTED, DriveEvent.DISARMED) and ctl.rearm_after_restart:
                if ev is DriveEvent.DSP_RESTARTED:
                    self.monitor.acknowledge_restart()
                dsp.enable(reset_fault=False)
                n.rearms += 1

    def block(self, dsp: JointClient) -> dict:
        """The ``dsp`` component of the ``/diagnostics`` record."""
        status = dsp.status
        return {
            "status_received": status is not None,
            "mode": self.monitor.mode,
            "drive_state": status.drive_state.label if status else "none",
            "fault_reason": status.fault_reason.label if status else "none",
            "session": int(status.session) if status else 0,
            "torque_enabled": bool(status and status.torque_enabled),
            "watchdog_tripped": bool(status and status.watchdog_tripped),
            "rejected_frames": int(status.rejected_frames) if status else 0,
            **{f"events.{k}": v for k, v in self.monitor.counters().items()},
            **{f"ticks.{k}": v for k, v in self.ctx.counters.drive_ticks.items()},
        }
