"""Hard-cadence timing: absolute monotonic deadlines, sleep then spin, missed periods skipped.

Tick k is released at ``start + k * period``. A tick that cannot start within its own period
(the previous one overran, or the wake-up came a period late) is skipped (counted in
``missed``), never run in a burst. The clock is a parameter so tests drive the
cadence with a fake clock and never sleep.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

Idle = Callable[[int], None]
"""Work to do while waiting for a release: called with an absolute time (ns) it must return
by (e.g. block on the input sockets until then and decode what arrives)."""


class Clock(Protocol):
    """Integer nanoseconds and a way to wait for an absolute time."""

    kernel_stamps: bool
    """The kernel's receive stamps of CAN frames are on this clock (else frames are stamped
    when read)."""
    spun_ns: int
    """Time spent busy-waiting for deadlines so far (the spin window's CPU, reported apart)."""

    def now_ns(self) -> int: ...

    def sleep_until(self, deadline_ns: int, idle: Idle | None = None) -> None: ...


class MonotonicClock:
    """``time.monotonic_ns`` with ``clock_nanosleep``-style waiting: sleep, then spin the rest."""

    kernel_stamps = True
    """A socket's receive stamps are wall-clock times the client moves onto this clock."""

    def __init__(self, spin_ns: int = 300_000) -> None:
        self.spin_ns = spin_ns
        self.spun_ns = 0
        """Time spent busy-waiting so far (the CPU the spin window costs, reported apart)."""

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def sleep_until(self, deadline_ns: int, idle: Idle | None = None) -> None:
        """Wait until ``deadline_ns``: sleep (or run ``idle`` repeatedly) until the spin
        window, then spin."""
        wake = deadline_ns - self.spin_ns
        if idle is None:
            remaining = wake - time.monotonic_ns()
            if remaining > 0:
                time.sleep(remaining / 1e9)
        else:
            while time.monotonic_ns() < wake:
                idle(wake)
        t0 = now = time.monotonic_ns()
        while now < deadline_ns:
            now = time.monotonic_ns()
        self.spun_ns += now - t0


@dataclass(frozen=True)
class Tick:
    """One release of the loop."""

    index: int
    """Tick number k (here: periods since start, skipped ones included)."""
    release_ns: int
    """When it was due (start + k * period)."""
    wake_ns: int
    """When the loop actually woke."""
    missed: int
    """Periods skipped just before it (an overrun, or Sync frames never seen)."""
    asked_ns: int | None = None
    """The release the wait slept until, when the wake-up came a whole period late and the
    tick took a later release (None: ``release_ns``)."""

    @property
    def lateness_ns(self) -> int:
        return self.wake_ns - self.release_ns

    @property
    def wake_lateness_ns(self) -> int:
        """How late the wake-up came for what the wait asked (the host's latency)."""
        return self.wake_ns - (self.release_ns if self.asked_ns is None else self.asked_ns)


class Cadence:
    """Absolute-deadline periodic releases on a :class:`Clock`."""

    def __init__(self, period_ns: int, clock: Clock, start_ns: int | None = None) -> None:
        if period_ns <= 0:
            raise ValueError(f"period must be positive, got {period_ns} ns")
        self.period_ns = period_ns
        self.clock = clock
        self.start_ns = clock.now_ns() + period_ns if start_ns is None else start_ns
        self._next = 0

    def wait(self, idle: Idle | None = None) -> Tick:
        """Sleep until the next release (running ``idle`` meanwhile, see :data:`Idle`); skip
        releases that already lie a period in the past, before the sleep and after it (a
        wake-up, or ``idle``, a whole period late: that release's period is over, the tick is
        the current period's, never a stale one followed at once by the next)."""
        k, asked, missed = self._current(self._next, self.clock.now_ns())
        self.clock.sleep_until(asked, idle)
        wake = self.clock.now_ns()
        k, release, late = self._current(k, wake)
        self._next = k + 1
        return Tick(k, release, wake, missed + late, asked if late else None)

    def _current(self, k: int, now_ns: int) -> tuple[int, int, int]:
        """Release ``k``, or the latest one at or before ``now_ns`` if ``now_ns`` lies past
        release k's period: (index, release time, releases skipped)."""
        release = self.start_ns + k * self.period_ns
        if now_ns < release + self.period_ns:
            return k, release, 0
        skipped = (now_ns - release) // self.period_ns
        return k + skipped, release + skipped * self.period_ns, skipped
