"""One run's shared context: what every part of the loop reads, passed as one typed object.

The pacer, the hardware profile, the drive policy and the loop all hold the same
:class:`RunContext`. The configuration in force lives here only: an accepted online parameter
change replaces ``ctx.cfg`` once (:meth:`rt_controller.runtime.loop.ControlLoop.take_parameters`)
and every part sees it from the next read on; no part keeps a copy.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from hal.config import RigConfig
from hal.hardware_interface import StopFlag
from rt_controller.runtime.cadence import Clock
from rt_controller.runtime.counters import RunCounters

if TYPE_CHECKING:
    from rt_controller.runtime.recorder import Recorder


@dataclass
class RunContext:
    """The parts of one run that every other part reads."""

    cfg: RigConfig
    """The configuration in force (replaced, never edited, by an accepted parameter change)."""
    clock: Clock
    """The loop's clock: every time stamp of the run."""
    stop: StopFlag
    """The run's stop request (signals, the plan, the tests)."""
    counters: RunCounters
    """The run's totals (the summary and ``/diagnostics``)."""
    recorder: Recorder
    """The run's log (its ``record_*`` calls, ``write`` and ``as_dict``; the live stream)."""
    say: Callable[[str], None] = lambda line: None
    """Tell the operator one line (the daemon's: on stderr), e.g. what a slow start-up awaits."""

    def pause(self, ns: int) -> None:
        """Wait ``ns`` on the loop's clock (start-up, arming in lockstep)."""
        self.clock.sleep_until(self.clock.now_ns() + ns)


__all__ = ["RunContext"]
