"""The DSP profile of the hardware seam (:class:`hal.hardware_interface.HardwareInterface`):
the emulated or real DSP of ``hal/hil.dbc`` over CAN, the image features over zenoh.

The CAN link is a :class:`~hal.joint_client.JointClient` in poll mode (read in the control
thread, no receive thread); the features come through a
:class:`~rt_controller.runtime.feature_link.FeatureLink` (the zenoh half every profile shares,
with the rest of :class:`~rt_controller.runtime.hardware_base.HardwareBase`). Every DspStatus
is followed by a :class:`~hal.drive_state.DriveMonitor`, which says in which mode each tick
runs and when the re-arm policy acts. In lockstep the DSP paces: :meth:`DspHardware.step`
waits for its ``Sync(k)``.
"""

from __future__ import annotations

import math
import time
from typing import Any

from hal.bus import resolve_spec
from hal.drive_state import MODE_ENABLED, DriveEvent, DriveMonitor, DriveUpdate, FaultReason
from hal.errors import HalTimeoutError
from hal.hardware_interface import InputJudge, Observation, StopFlag
from hal.joint_client import JointClient
from rt_controller.errors import ControllerError
from rt_controller.runtime import diagnostics
from rt_controller.runtime.context import RunContext
from rt_controller.runtime.feature_link import FeatureLink
from rt_controller.runtime.hardware_base import ENABLE_TIMEOUT_S, NOTICE_AFTER_S, HardwareBase
from rt_controller.runtime.pacers import LOCKSTEP_FEATURE_TIMEOUT_S

STARTUP_TIMEOUT_S = 20.0
"""How long start-up waits for the first joint state and features before giving up."""
ARMING_COMMANDS = 8
"""Realtime: zero torques sent while arming, at least: the DSP learns the cycle's phase from the
earliest of its recent commands, so a slow first law frame does not place the scenario's t = 0
late (which would delay every torque of the run by as much)."""
PREFETCH_GUARD_NS = 1_000_000
"""Realtime: the read-ahead between releases stops this long before the next release."""


class DspHardware(HardwareBase):
    """CAN and zenoh of one run, read and written from the control thread.

    Re-arm policy (``controller.rearm_after_trip``, ``controller.rearm_after_restart``): a
    watchdog fault means this loop was late, so it may be reset and re-armed once per trip; a
    DSP that restarted (new session) or was disabled by someone else is re-armed only when
    configured; a limit or encoder fault never is; after the operator's ``disarm`` none is.
    """

    def __init__(
        self,
        ctx: RunContext,
        dsp: JointClient,
        features: FeatureLink,
        *,
        lockstep: bool,
        record_raw: bool,
    ) -> None:
        """``lockstep``: the DSP's Sync paces (features by callback, no cyclic arming)."""
        super().__init__(ctx, features, lockstep=lockstep, record_raw=record_raw)
        self.dsp = dsp
        self.monitor = DriveMonitor()
        self.held_off = False
        """The operator disarmed the DSP: no policy re-arm until the operator arms it."""
        self.can_base = dsp.stats.e2e.as_dict()
        """The CAN receive counters when this run began (a plan's links outlive its runs)."""
        self._arming_sent = 0
        self._last_sync: int | None = None
        self._states_at_step = dsp.states_received  # since then: a realtime DSP's, if any
        self.last_tau = (0.0, 0.0)
        """Lockstep: the last torque sent, sent again when the DSP re-sends its Sync."""

    # --- lifecycle --------------------------------------------------------------------------
    def configure(self, stop: StopFlag) -> None:
        """Subscribe this run to the features (and the camera's images, when logged), hook
        the raw CAN log, then wait for the DSP's first joint state (and, read by ring, the
        first features)."""
        self.features.attach()
        self._hook_raw_can(self.dsp.bus)
        self._wait_ready(stop, features=not self.lockstep)

    def activate(self, now_ns: int) -> bool:
        """ENABLE on the first call, then (realtime) a zero torque (Enable = 0) at every call,
        until the DSP reports *operation enabled* and has had ``ARMING_COMMANDS`` of them. The
        command stream is cyclic from ENABLE on (the DSP arms its watchdog there); the zeros
        teach the DSP the cycle's phase, on which the emulated DSP places the scenario's t = 0
        when the first law tick's frame applies torque. Counted in ``arming_ticks``."""
        clock, dsp = self.ctx.clock, self.dsp
        expired = self._enable_by is not None and clock.now_ns() > self._enable_by
        self._poll(clock.now_ns())
        needed = 0 if self.lockstep else ARMING_COMMANDS
        if self._enabled_now(expired) and self._arming_sent >= needed:
            return True
        if self._enable_by is None:
            dsp.enable()
            self._start_arming()
        if not self.lockstep:
            delay = (clock.now_ns() - now_ns) // 1000
            dsp.send_torque(0.0, 0.0, release_delay_us=delay, enable=False)
            self._arming_sent += 1
            self.ctx.counters.arming_ticks += 1
        self._arrived(dsp.states_received)
        return False

    def _disarm(self) -> None:
        self.dsp.send_torque(0.0, 0.0)
        self.dsp.disable()

    # --- pacing -----------------------------------------------------------------------------
    def wait_inputs(self, until_ns: int) -> None:
        """Realtime, between releases: block on the CAN socket and decode what arrives, so the
        tick finds it decoded; no decode starts within ``PREFETCH_GUARD_NS`` (at most a
        quarter period) of ``until_ns``."""
        now = self.ctx.clock.now_ns()
        guard_ns = min(PREFETCH_GUARD_NS, self.ctx.cfg.rates.control_period_ns // 4)
        stop_ns = until_ns - guard_ns
        if now >= stop_ns:
            time.sleep(max(0, until_ns - now) / 1e9)
        elif self.dsp.wait_readable((stop_ns - now) / 1e9):
            self._poll(self.ctx.clock.now_ns())

    def step(self, timeout_s: float) -> int | None:
        """Lockstep: the next new ``Sync(k)`` of the DSP (a re-sent one, whose command was
        lost, gets the last torque again), then the features answering pose k; k, or None
        when no Sync came within ``timeout_s``."""
        while True:
            try:
                k = self.dsp.wait_sync(timeout_s)
            except HalTimeoutError:
                return None
            last = self._last_sync
            if last is None or k > last:
                break
            if k == last:  # a re-sent Sync: our command was lost, send it again
                self.dsp.send_torque(*self.last_tau, tick=k)
        self._last_sync, self._states_at_step = k, self.dsp.states_received
        self.features.wait_pose(k, LOCKSTEP_FEATURE_TIMEOUT_S)
        return k

    def why_silent(self) -> str:
        """Lockstep without a Sync: the joint states that kept coming are a realtime DSP's."""
        if self.dsp.states_received > self._states_at_step:
            return " (its joint states arrive: is the emulator started with --lockstep?)"
        return ""

    # --- read and write ---------------------------------------------------------------------
    def read(self, now_ns: int, judge: InputJudge) -> Observation:
        """Everything waiting on the links taken off, the drive state followed to ``now_ns``,
        the newest joint state and features judged stale or fresh by ``judge``."""
        self._poll(self.ctx.clock.now_ns())  # stamped when actually read, not at the wake-up
        dsp = self.dsp
        state_new = self._arrived(dsp.states_received)
        mode = self._follow(now_ns, judge.status_limit_s)
        try:
            state = dsp.latest_state(max_age_s=judge.state_limit_s, now_ns=now_ns)
        except HalTimeoutError:
            return self._observation(now_ns, judge, None, None, math.nan, mode, state_new)
        age_ms = (now_ns - state.t_ns) / 1e6
        return self._observation(now_ns, judge, state, state.t_ns, age_ms, mode, state_new)

    def write(self, tau: tuple[float, float], *, sync: int | None, release_ns: int) -> None:
        """Send the tick's torque: answering Sync ``sync`` when given, else carrying how long
        after its release it left (realtime, ``TorqueCommand.Tick``)."""
        t1, t2 = self.last_tau = tau
        if sync is not None:
            self.dsp.send_torque(t1, t2, tick=sync)
        else:
            delay = (self.ctx.clock.now_ns() - release_ns) // 1000
            self.dsp.send_torque(t1, t2, release_delay_us=delay)

    # --- the drive state (every DspStatus followed) -----------------------------------------
    def _enabled_now(self, expired: bool) -> bool:
        """During arming: whether the DSP reports *operation enabled* (its statuses are
        followed, not acted on: ENABLE resets); raises once ``expired`` and it does not."""
        status = self.dsp.status
        for st in self.dsp.take_statuses():
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

    def _follow(self, now_ns: int, status_limit_s: float | None) -> str:
        """Feed every status since the last read to the monitor, in order, acting on each
        update's events (a fault, reset and enable that arrived between two reads are all
        seen); the drive mode of this tick. A status older than ``status_limit_s`` means a
        silent DSP (None: no limit, the pacer's clock already proves the DSP alive)."""
        for status in self.dsp.take_statuses():
            self._on_events(self.monitor.update(status))
        silent = False
        if status_limit_s is not None:
            age = self.dsp.status_age_s_at(now_ns)
            silent = age is None or age > status_limit_s
        return self._tick_mode(self.monitor.mode, silent)

    def _on_events(self, upd: DriveUpdate) -> None:
        ctl, n, dsp = self.ctx.cfg.controller, self.ctx.counters, self.dsp
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

    def command(self, action: str) -> str | None:
        """An operator's ``arm``, ``disarm`` or ``mark`` (nothing to do); None when done,
        else why not."""
        if action == "disarm":
            if self.held_off:
                return "already disarmed by the operator"
            self.held_off = True
            self.dsp.disable()
        elif action == "arm":
            if not self.held_off and self.monitor.mode == MODE_ENABLED:
                return "already armed"
            self.held_off = False
            self.dsp.enable(reset_fault=True)
        return None

    def diagnostics(self) -> dict[str, dict[str, Any]]:
        """The receive verdicts of this run (``can_rx``, with the link's driver errors, cut
        drains and foreign stamps when there were any; ``features``) and the drive (``dsp``:
        its last status, the monitor's events, the run's ticks by drive mode)."""
        status, st = self.dsp.status, self.dsp.stats
        link = {"transport_errors": st.transport_errors, "drains_cut": st.drains_cut}
        link["foreign_stamps"] = st.foreign_stamps
        return {
            "can_rx": {
                **diagnostics.since(self.can_base, st.e2e.as_dict()),
                **{k: v for k, v in link.items() if v},
            },
            "features": self.features.as_dict(),
            "dsp": {
                "status_received": status is not None,
                "mode": self.monitor.mode,
                "drive_state": status.drive_state.label if status else "none",
                "fault_reason": status.fault_reason.label if status else "none",
                "session": int(status.session) if status else 0,
                "torque_enabled": bool(status and status.torque_enabled),
                "watchdog_tripped": bool(status and status.watchdog_tripped),
                "rejected_frames": int(status.rejected_frames) if status else 0,
                **{f"events.{k}": v for k, v in self.monitor.as_dict().items()},
                **{f"ticks.{k}": v for k, v in self.ctx.counters.drive_ticks.items()},
            },
        }

    # --- links ------------------------------------------------------------------------------
    def _wait_ready(self, stop: StopFlag, *, features: bool) -> None:
        """Until the first joint state (and, with ``features``, image features)."""
        start = time.monotonic()
        deadline, notice_at = start + STARTUP_TIMEOUT_S, start + NOTICE_AFTER_S
        while not stop.is_set():
            self._poll(self.ctx.clock.now_ns())
            have_state = self.dsp.state_age_s() is not None
            need_f = features and self.features.features.latest is None
            if have_state and not need_f:
                return
            if time.monotonic() > notice_at:  # say once what is still missing
                notice_at, t = math.inf, self.ctx.cfg.transport
                what = [] if have_state else [f"the first joint state on CAN {resolve_spec(t.can)}"]
                if need_f:
                    what.append(f"image features on zenoh {t.zenoh_config or t.zenoh_endpoint}")
                away = f"; so far {a}" if (a := self._turned_away()) else ""
                self.ctx.say(
                    f"waiting for {' and '.join(what)} (up to {STARTUP_TIMEOUT_S:g} s){away}"
                )
            if time.monotonic() > deadline:
                missing = "joint state (CAN)" if not have_state else "image features (zenoh)"
                status = self.dsp.status  # a lockstep world waits, without a pose, for a step
                why = (
                    "the DSP runs lockstep (`hil emulator --lockstep`): use --clock lockstep"
                    if status is not None and status.lockstep and not self.lockstep
                    else self._turned_away() or self._nothing_came(have_state)
                )
                raise ControllerError(f"no {missing} within {STARTUP_TIMEOUT_S:.0f} s: {why}")
            self.ctx.pause(10_000_000)

    def _nothing_came(self, have_state: bool) -> str:
        """Where the input that never came was awaited, and what should be sending it."""
        t = self.ctx.cfg.transport
        if not have_state:
            return (
                f"nothing came on CAN {resolve_spec(t.can)}: is a DSP sending there (`hil "
                "emulator` on the same --can, or the rig's DSP powered, on that bus, at its bit "
                "rates)?"
            )
        return (
            f"nothing came on zenoh {t.zenoh_config or t.zenoh_endpoint}: is `hil vision` "
            "running there (the same --zenoh-endpoint)?"
        )

    def _turned_away(self) -> str:
        """:func:`turned_away` of the DSP's frames and the features so far."""
        return turned_away(
            self.dsp.stats.e2e.rejections(), self.features.features.counts.rejections()
        )

    def _poll(self, now_ns: int) -> None:
        """Take every CAN frame waiting on the bus and the newest feature messages off the
        transports, into their decoders (stamped ``now_ns`` where the clock has no kernel
        stamps)."""
        self.dsp.drain(now_ns, timestamps=self.ctx.clock.kernel_stamps)
        self.features.poll(now_ns)


def turned_away(can: dict[str, int], features: dict[str, int]) -> str:
    """What came at start-up and was rejected, by reason, with the likeliest cause (then the
    inputs arrive and are all refused); empty when nothing was."""
    said = [
        f"{sum(c.values())} {what} rejected ({', '.join(f'{k} {n}' for k, n in c.items())})"
        for what, c in (("DSP frames", can), ("feature messages", features))
        if c
    ]
    if "bad_mac" in can or "bad_mac" in features:
        said.append("signed with another rig key? (every process needs the same --key-file)")
    elif {"stale_freshness", "future_freshness"} & can.keys():
        said.append("is the DSP's clock within 1 s of this host's? (SecOC freshness: PTP/NTP)")
    elif "future_stamp" in features:  # capture stamps are the capturing host's CLOCK_MONOTONIC
        said.append(
            "features stamped ahead of this host's monotonic clock: a camera must run on the "
            "controller's host (no two hosts share a monotonic clock)"
        )
    return "; ".join(said)


__all__ = ["STARTUP_TIMEOUT_S", "DspHardware", "turned_away"]
