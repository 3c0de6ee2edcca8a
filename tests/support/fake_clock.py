"""A fake loop clock (:class:`rt_controller.runtime.cadence.Clock`): tests drive the cadence and
the daemon with it and never sleep."""

from __future__ import annotations

from rt_controller.runtime.cadence import Idle


class FakeClock:
    """A clock that jumps to each deadline instantly; ``advance`` simulates work."""

    kernel_stamps = False
    """Frames are stamped when read: the kernel's stamps are not on this clock."""
    spun_ns = 0
    """It never busy-waits."""

    def __init__(self, start_ns: int = 0, wake_latency_ns: int = 0) -> None:
        self.t = start_ns
        self.wake_latency_ns = wake_latency_ns

    def now_ns(self) -> int:
        return self.t

    def sleep_until(self, deadline_ns: int, idle: Idle | None = None) -> None:
        """Jump to the deadline (``idle`` is not run: nothing arrives in no time)."""
        if deadline_ns > self.t:
            self.t = deadline_ns + self.wake_latency_ns

    def advance(self, ns: int) -> None:
        self.t += ns
