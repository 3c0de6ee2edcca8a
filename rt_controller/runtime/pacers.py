"""When ticks happen: one pacer per clock mode, the only place the mode makes a difference.

* :class:`RealtimePacer`: absolute monotonic releases (sleep, then spin ``controller.spin_us``),
  an overrun skips periods, the wait for a release reads the inputs as they arrive and
  rehearses the last tick just before it;
* :class:`LockstepPacer`: one tick per DSP ``Sync(k)``, after the features that answer the
  same period.

A pacer arms the DSP, yields each :class:`Release`, and says how inputs are aged in its mode.
"""

from __future__ import annotations

import enum
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

from hal.config import RigConfig
from hal.errors import HalTimeoutError
from hal.vision_codec import FeatureMsg, feature_age_ns
from rt_controller.runtime.cadence import Cadence, Clock, Tick
from rt_controller.runtime.counters import RunCounters
from rt_controller.runtime.drive_policy import ENABLE_TIMEOUT_S, DrivePolicy
from rt_controller.runtime.hardware import Observation, RigHardware

LOCKSTEP_SYNC_TIMEOUT_S = 2.0
"""Lockstep without a duration: without a Sync for this long the emulator has finished."""
LOCKSTEP_STALL_TIMEOUT_S = 30.0
"""Lockstep with a duration not yet reached: how long the DSP may stay silent (a stalled
emulator; user-mode Linux runs about 10x slower) before the run ends short (not clean)."""
LOCKSTEP_FEATURE_TIMEOUT_S = 1.0
"""Lockstep: how long a tick waits for the features answering its period's pose."""
SYNC_POLL_S = 0.25
"""Lockstep: the wait for a Sync looks at the stop request this often."""
PREFETCH_GUARD_NS = 1_000_000
"""Realtime: the read-ahead while waiting for a release stops this long before the spin window."""
ARMING_COMMANDS = 8
"""Realtime: zero torques sent while arming, at least: the DSP learns the cycle's phase from the
earliest of its recent commands, so a slow first law frame does not place the scenario's t = 0
late (which would delay every torque of the run by as much)."""
REHEARSAL_LEAD_NS = 200_000
"""Realtime: the rehearsal of the last tick starts this long before the spin window."""


class ClockMode(enum.Enum):
    """What paces the loop: the host's monotonic clock, or the DSP's Sync frames."""

    REALTIME = "realtime"
    LOCKSTEP = "lockstep"


@dataclass(frozen=True)
class Release(Tick):
    """One tick's start, as its pacer gives it (``index``: realtime, periods since the first
    law tick; lockstep, Sync k; times on the loop's clock)."""

    t_s: float = 0.0
    """Run time of the tick (s): 0 at the first law tick, k periods later at tick k."""
    sync: int | None = None
    """The Sync it answers (lockstep), None in realtime."""


class _Pacer:
    """What both pacers hold: the run's parts they drive."""

    def __init__(
        self,
        cfg: RigConfig,
        clock: Clock,
        hw: RigHardware,
        drive: DrivePolicy,
        counters: RunCounters,
        stop: Any,
    ) -> None:
        self.cfg, self.clock, self.hw, self.drive = cfg, clock, hw, drive
        self.counters, self.stop = counters, stop
        self.period_ns = cfg.rates.control_period_ns

    def retune(self, cfg: RigConfig) -> None:
        """Run with ``cfg`` (online parameters) from the next release on."""
        self.cfg = cfg


class RealtimePacer(_Pacer):
    """Hard cadence on the loop's clock (see the module docstring)."""

    mode = ClockMode.REALTIME
    features_by_callback = False
    """The tick takes the newest features off a ring itself (no callback thread)."""

    def __init__(self, *parts: Any, real_clock: bool) -> None:
        """``parts``: those of every pacer; ``real_clock``: the wait reads the inputs ahead (a
        fake clock's waits take no time)."""
        super().__init__(*parts)
        cfg = self.cfg
        self.state_limit_s = cfg.controller.state_timeout_s
        self.status_limit_s: float | None = 3.0 / cfg.rates.status_hz
        """A DspStatus older than three status periods means the DSP went silent."""
        self.cadence = Cadence(self.period_ns, self.clock)
        self._real_clock = real_clock
        self.rehearse: Callable[[], None] | None = None
        """Rerun the last tick just before each release (None: never; see
        :mod:`rt_controller.runtime.rehearsal`)."""
        self._rehearsal_due = False
        self._states_seen = -1

    def retune(self, cfg: RigConfig) -> None:
        """From the next release on, ``cfg``'s state timeout and predictions too."""
        self.cfg, self.state_limit_s = cfg, cfg.controller.state_timeout_s

    def feature_age_ms(self, feat: FeatureMsg, recv_ns: int, wake_ns: int) -> float:
        """By stamp and by arrival: a future stamp cannot make old data look fresh."""
        return feature_age_ns(wake_ns, feat.stamp_ns, recv_ns) / 1e6

    def prediction_ms(self, obs: Observation) -> tuple[float, float]:
        """How far the joint state and features are brought forward: their ages, when fresh
        (``controller.predict_state``, ``controller.predict_features``)."""
        ctl = self.cfg.controller
        state = obs.state_age_ms if ctl.predict_state and not obs.state_stale else 0.0
        feats = obs.f_age_ms if ctl.predict_features and not obs.f_stale else 0.0
        return (
            state if math.isfinite(state) and state > 0 else 0.0,
            feats if math.isfinite(feats) and feats > 0 else 0.0,
        )

    def releases(self, max_ticks: int | None) -> Iterator[Release]:
        """Arm the DSP on the cadence, then one release per period from the first at which
        it reported enabled (tick 0, t = 0) until ``max_ticks`` or a stop."""
        try:
            first = self._arm()
            if first is None:
                return
            tick = first
            while not self.stop.is_set():
                index = tick.index - first.index
                # the inputs are stamped when actually read (a preempted tick reads later
                # than it woke): a message that arrived after the wake-up is not "from the future"
                self.hw.poll(self.clock.now_ns())
                if self.hw.dsp.states_received == self._states_seen:  # this period's is late
                    self.counters.late_states += 1
                self._states_seen = self.hw.dsp.states_received
                yield Release(
                    index=index,
                    t_s=(tick.release_ns - first.release_ns) / 1e9,
                    release_ns=tick.release_ns,
                    wake_ns=tick.wake_ns,
                    missed=tick.missed,
                )
                if max_ticks is not None and index + 1 >= max_ticks:
                    return  # the last tick ran: no release to wait for
                self._rehearsal_due = self.rehearse is not None
                tick = self.cadence.wait(self._idle)
        finally:
            self.counters.spin_s = getattr(self.clock, "spun_ns", 0) / 1e9

    def overran(self, release: Release) -> bool:
        """Whether the tick's work ran past the next release (its deadline)."""
        return self.clock.now_ns() > release.release_ns + self.period_ns

    def _arm(self) -> Tick | None:
        """ENABLE at the first release, then a zero torque (Enable = 0) at every release until
        the DSP reports *operation enabled* and has had ``ARMING_COMMANDS`` of them; that
        release (its tick runs the law), or None when told to stop first. The command stream
        is cyclic from ENABLE on (the DSP arms its watchdog there); the zeros teach the DSP the
        cycle's phase, on which the emulated DSP places the scenario's t = 0 when the first law
        tick's frame applies torque. Counted in ``arming_ticks``."""
        deadline: int | None = None
        dsp = self.hw.dsp
        sent = 0
        while not self.stop.is_set():
            tick = self.cadence.wait()
            expired = deadline is not None and self.clock.now_ns() > deadline
            self.hw.poll(self.clock.now_ns())
            if self.drive.enabled_now(dsp, expired) and sent >= ARMING_COMMANDS:
                return tick
            if deadline is None:
                dsp.enable()
                deadline = self.clock.now_ns() + round(ENABLE_TIMEOUT_S * 1e9)
            delay = (self.clock.now_ns() - tick.release_ns) // 1000
            dsp.send_torque(0.0, 0.0, release_delay_us=delay, enable=False)
            sent += 1
            self._states_seen = dsp.states_received
            self.counters.arming_ticks += 1
        return None

    def _idle(self, until_ns: int) -> None:
        """The wait for a release: on the real clock, read the inputs as they arrive
        (blocking on the CAN socket), so the tick finds them decoded; no decode starts within
        ``PREFETCH_GUARD_NS`` (at most a quarter period) of the spin window; then the
        rehearsal, ``REHEARSAL_LEAD_NS`` before it. A fake clock rehearses at once."""
        now = self.clock.now_ns()
        if not self._real_clock:
            self._rehearse_if_due()
            return
        guard_ns = min(PREFETCH_GUARD_NS, self.period_ns // 4)
        stop_ns = until_ns - guard_ns
        if now < stop_ns:
            if self.hw.dsp.wait_readable((stop_ns - now) / 1e9):
                self.hw.poll(self.clock.now_ns())
            return
        if self._rehearsal_due:
            at = until_ns - REHEARSAL_LEAD_NS
            if now < at:
                time.sleep((at - now) / 1e9)
            self._rehearse_if_due()
            return
        time.sleep(max(0, until_ns - now) / 1e9)

    def _rehearse_if_due(self) -> None:
        if self._rehearsal_due and self.rehearse is not None:
            self._rehearsal_due = False
            self.rehearse()


class LockstepPacer(_Pacer):
    """One tick per DSP Sync (see the module docstring)."""

    mode = ClockMode.LOCKSTEP
    features_by_callback = True
    """The tick waits for its pose's answer: a callback feeds the features as they come."""
    state_limit_s = LOCKSTEP_SYNC_TIMEOUT_S + LOCKSTEP_FEATURE_TIMEOUT_S
    """The DSP announces the state with every Sync, so its wall-clock age only reflects how
    long this tick waited (for features); a silent DSP ends the run instead."""
    status_limit_s = None
    """Without a live DSP there is no Sync and no tick: no status age limit."""

    def __init__(self, *parts: Any, pause: Callable[[int], None]) -> None:
        """``parts``: those of every pacer; ``pause(ns)`` waits during arming."""
        super().__init__(*parts)
        self.pause = pause

    def feature_age_ms(self, feat: FeatureMsg, recv_ns: int, wake_ns: int) -> float:
        """In simulation time, at the tick's own time (set by :meth:`releases`)."""
        # in integer ns: t_s * 1e9 rounds below k * period_ns at some ticks (4.02 s, ...), and
        # a frame captured at the tick itself came out 5e-13 ms "in the future": stale
        return (self._now_sim_ns - feat.sim_time_ns) / 1e6

    def prediction_ms(self, obs: Observation) -> tuple[float, float]:
        """Nothing to bring forward: state and features are sampled at the tick."""
        return 0.0, 0.0

    def overran(self, release: Release) -> bool:
        """No deadlines: the DSP waits for the tick."""
        return False

    def releases(self, max_ticks: int | None) -> Iterator[Release]:
        """ENABLE and wait for *operation enabled* (the lockstep DSP advances no period
        before), then one release per new Sync (a re-sent one gets the last torque again)."""
        self.hw.dsp.enable()
        self._wait_enabled()
        last = None
        patience = LOCKSTEP_SYNC_TIMEOUT_S if max_ticks is None else LOCKSTEP_STALL_TIMEOUT_S
        while not self.stop.is_set() and (max_ticks is None or self.counters.ticks < max_ticks):
            k = self._next_sync(patience)
            if k is None:
                return
            if last is not None and k <= last:
                if k == last:  # a re-sent Sync: our command was lost, send it again
                    self.hw.resend(k)
                continue
            missed = 0 if last is None else k - last - 1
            last = k
            wake = self.clock.now_ns()
            self.hw.features.wait_pose_seq(k, LOCKSTEP_FEATURE_TIMEOUT_S)
            self.hw.poll(self.clock.now_ns())
            self._now_sim_ns = k * self.period_ns
            yield Release(
                index=k,
                t_s=k * self.period_ns / 1e9,
                release_ns=wake,
                wake_ns=wake,
                missed=missed,
                sync=k,
            )

    def _wait_enabled(self) -> None:
        deadline = time.monotonic() + ENABLE_TIMEOUT_S
        while not self.stop.is_set():
            self.hw.poll(self.clock.now_ns())
            if self.drive.enabled_now(self.hw.dsp, time.monotonic() > deadline):
                return
            self.pause(1_000_000)

    def _next_sync(self, patience_s: float) -> int | None:
        """The next Sync's tick (the bus is read in this thread); None when told to stop or
        when the DSP stayed silent for ``patience_s`` (``end_reason`` says which)."""
        waited = 0.0
        while not self.stop.is_set():
            try:
                return self.hw.dsp.wait_sync(SYNC_POLL_S)
            except HalTimeoutError:
                waited += SYNC_POLL_S
            if waited >= patience_s:
                if self.counters.planned_ticks is not None:
                    self.counters.end_reason = f"no Sync from the DSP for {patience_s:g} s"
                return None
        return None


Pacer = RealtimePacer | LockstepPacer

__all__ = ["ClockMode", "LockstepPacer", "Pacer", "RealtimePacer", "Release"]
