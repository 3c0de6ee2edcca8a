"""When ticks happen: one pacer per clock mode, the only place the mode makes a difference.

* :class:`RealtimePacer`: absolute monotonic releases (sleep, then spin ``controller.spin_us``),
  an overrun skips periods; the wait for a release runs the hardware's read-ahead;
* :class:`LockstepPacer`: one release per period the hardware steps to (the DSP's ``Sync(k)``).

A pacer only yields times: :meth:`arming` the times of the arming steps (the loop calls the
hardware's ``activate`` at each), then :meth:`releases` one :class:`Release` per tick. It also
says how inputs are aged in its mode (it is the hardware's
:class:`~hal.hardware_interface.InputJudge`). It never touches a link.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from hal.hardware_interface import Observation
from hal.vision_codec import FeatureMsg
from hal.vision_receivers import feature_age_ns
from rt_controller.runtime.cadence import Cadence, Idle, Tick
from rt_controller.runtime.context import RunContext

LOCKSTEP_SYNC_TIMEOUT_S = 2.0
"""Lockstep without a duration: without a step for this long the emulator has finished."""
LOCKSTEP_STALL_TIMEOUT_S = 30.0
"""Lockstep with a duration not yet reached: how long the world may stay silent (a stalled
emulator; user-mode Linux runs about 10x slower) before the run ends short (not clean)."""
LOCKSTEP_FEATURE_TIMEOUT_S = 1.0
"""Lockstep: how long a step may wait for the features answering its period's pose."""
STEP_POLL_S = 0.25
"""Lockstep: the wait for a step looks at the stop request this often."""
NO_SYNC_HINT = (
    "; none came since the start: start `hil emulator --lockstep` on the same --can and rig"
    " key, or the whole rig with `hil up --lockstep`"
)
"""Lockstep: appended to the end reason when no Sync came since the run started."""
ARMING_POLL_NS = 1_000_000
"""Lockstep: arming steps this far apart (the world does not step before it is armed)."""


@dataclass(frozen=True)
class Release(Tick):
    """One tick's start, as its pacer gives it (``index``: realtime, periods since the first
    law tick; lockstep, the step k; times on the loop's clock)."""

    t_s: float = 0.0
    """Run time of the tick (s): 0 at the first law tick, k periods later at tick k."""
    sync: int | None = None
    """The step it answers (lockstep), None in realtime."""


class RealtimePacer:
    """Hard cadence on the loop's clock (see the module docstring)."""

    def __init__(self, ctx: RunContext, idle: Idle) -> None:
        """``idle``: the work of the wait for a release (the hardware's ``wait_inputs``)."""
        self.ctx = ctx
        self.idle = idle
        self.period_ns = ctx.cfg.rates.control_period_ns
        self.cadence = Cadence(self.period_ns, ctx.clock)
        self._last: Tick | None = None

    @property
    def state_limit_s(self) -> float:
        return self.ctx.cfg.controller.state_timeout_s

    @property
    def status_limit_s(self) -> float:
        """A status older than three status periods means the drive went silent."""
        return 3.0 / self.ctx.cfg.rates.status_hz

    def feature_age_ms(self, feat: FeatureMsg, recv_ns: int, wake_ns: int) -> float:
        """By stamp and by arrival: a future stamp cannot make old data look fresh."""
        return feature_age_ns(wake_ns, feat.stamp_ns, recv_ns) / 1e6

    def prediction_ms(self, obs: Observation) -> tuple[float, float]:
        """How far the joint state and features are brought forward: their ages and the
        hardware's actuation delay, when fresh."""
        return _prediction_ms(self.ctx, obs, obs.state_age_ms, obs.f_age_ms)

    def arming(self) -> Iterator[int]:
        """One arming step per period on the cadence (the command stream is cyclic from the
        first on): each one's release time."""
        while not self.ctx.stop.is_set():
            self._last = self.cadence.wait()
            if self.ctx.stop.is_set():
                return  # the stop came during the wait: no further arming step
            yield self._last.release_ns

    def releases(self, max_ticks: int | None) -> Iterator[Release]:
        """One release per period from the last arming step's (tick 0, t = 0: armed there)
        until ``max_ticks`` periods or a stop. A skip never runs a tick at or past period
        ``max_ticks`` (the duration's end); periods skipped before tick 0 (start-up, arming)
        are not periods of the run: tick 0 has none missed."""
        first = tick = self._first()
        while not self.ctx.stop.is_set():
            index = tick.index - first.index
            if max_ticks is not None and index >= max_ticks:
                return  # skipped past the end (or no tick planned at all)
            yield Release(
                index=index,
                t_s=(tick.release_ns - first.release_ns) / 1e9,
                release_ns=tick.release_ns,
                wake_ns=tick.wake_ns,
                missed=tick.missed if index else 0,
            )
            if max_ticks is not None and index + 1 >= max_ticks:
                return  # the last tick ran: no release to wait for
            tick = self.cadence.wait(self.idle)

    def _first(self) -> Tick:
        """Tick 0: the release of the arming step that armed, woken now (after that step's
        work); the current period's release instead when that work took the whole period (two
        commands in one period otherwise)."""
        armed, now = self._last, self.ctx.clock.now_ns()
        if armed is None or now >= armed.release_ns + self.period_ns:
            return self.cadence.wait()
        return Tick(armed.index, armed.release_ns, now, 0)

    def overran(self, release: Release) -> bool:
        """Whether the tick's work ran past the next release (its deadline)."""
        return self.ctx.clock.now_ns() > release.release_ns + self.period_ns


class LockstepPacer:
    """One tick per step of the world (see the module docstring)."""

    state_limit_s = LOCKSTEP_SYNC_TIMEOUT_S + LOCKSTEP_FEATURE_TIMEOUT_S
    """The world announces the state with every step, so its wall-clock age only reflects how
    long this tick waited (for features); a silent world ends the run instead."""
    status_limit_s = None
    """Without a live drive there is no step and no tick: no status age limit."""

    def __init__(
        self, ctx: RunContext, step: Callable[[float], int | None], why_silent: Callable[[], str]
    ) -> None:
        """``step(timeout_s)``: the hardware's next period k, None on timeout; ``why_silent()``:
        the hardware's hint for a world that stopped stepping ("" if none)."""
        self.ctx = ctx
        self.step = step
        self.why_silent = why_silent
        self.period_ns = ctx.cfg.rates.control_period_ns
        self._now_sim_ns = 0

    def feature_age_ms(self, feat: FeatureMsg, recv_ns: int, wake_ns: int) -> float:
        """In simulation time, at the tick's own time (set by :meth:`releases`)."""
        # in integer ns: t_s * 1e9 rounds below k * period_ns at some ticks (4.02 s, ...), and
        # a frame captured at the tick itself came out 5e-13 ms "in the future": stale
        return (self._now_sim_ns - feat.sim_time_ns) / 1e6

    def prediction_ms(self, obs: Observation) -> tuple[float, float]:
        """State and features are sampled at the tick: only the hardware's actuation delay
        (CiA 402: one period) is brought forward, by the same switches as in realtime."""
        return _prediction_ms(self.ctx, obs, 0.0, 0.0)

    def overran(self, release: Release) -> bool:
        """No deadlines: the world waits for the tick."""
        return False

    def arming(self) -> Iterator[int]:
        """Arming steps ``ARMING_POLL_NS`` apart: the world waits, unstepped, until armed."""
        while not self.ctx.stop.is_set():
            yield self.ctx.clock.now_ns()
            self.ctx.pause(ARMING_POLL_NS)

    def releases(self, max_ticks: int | None) -> Iterator[Release]:
        """One release per new step, until ``max_ticks`` ticks ran or the world fell silent."""
        last = None
        counters = self.ctx.counters
        patience = LOCKSTEP_SYNC_TIMEOUT_S if max_ticks is None else LOCKSTEP_STALL_TIMEOUT_S
        while not self.ctx.stop.is_set() and (max_ticks is None or counters.ticks < max_ticks):
            k = self._next_step(patience, first=last is None)
            if k is None:
                return
            missed = 0 if last is None else k - last - 1
            last = k
            wake = self.ctx.clock.now_ns()
            self._now_sim_ns = k * self.period_ns
            yield Release(
                index=k,
                t_s=k * self.period_ns / 1e9,
                release_ns=wake,
                wake_ns=wake,
                missed=missed,
                sync=k,
            )

    def _next_step(self, patience_s: float, *, first: bool) -> int | None:
        """The next step's k; None when told to stop or when the world stayed silent for
        ``patience_s`` (``end_reason`` says which: without a duration, silence after the first
        step is the world's end, silence before it is not)."""
        waited = 0.0
        while not self.ctx.stop.is_set():
            k = self.step(STEP_POLL_S)
            if k is not None:
                return k
            waited += STEP_POLL_S
            if waited >= patience_s:
                if first or self.ctx.counters.planned_ticks is not None:
                    why = f"no Sync from the DSP for {patience_s:g} s{self.why_silent()}"
                    self.ctx.counters.end_reason = why + (NO_SYNC_HINT if first else "")
                return None
        return None


def _prediction_ms(
    ctx: RunContext, obs: Observation, state_age_ms: float, f_age_ms: float
) -> tuple[float, float]:
    """The state's and the features' ages plus the actuation delay, each where its switch is
    on (``controller.predict_state``, ``controller.predict_features``) and the input fresh;
    0 where that is not a positive number."""
    ctl, delay = ctx.cfg.controller, obs.actuation_delay_ms
    state = state_age_ms + delay if ctl.predict_state and not obs.state_stale else 0.0
    feats = f_age_ms + delay if ctl.predict_features and not obs.f_stale else 0.0
    return (
        state if math.isfinite(state) and state > 0 else 0.0,
        feats if math.isfinite(feats) and feats > 0 else 0.0,
    )


Pacer = RealtimePacer | LockstepPacer

__all__ = ["LockstepPacer", "Pacer", "RealtimePacer", "Release"]
