"""The hand-over from any thread to the control thread at a tick boundary, shared by parameter
change sets and operator actions."""

from __future__ import annotations

import queue
from dataclasses import dataclass, field
from typing import Generic, Protocol, TypeVar


class Timed(Protocol):
    at_tick: int | None


T = TypeVar("T", bound=Timed)


@dataclass
class DueQueue(Generic[T]):
    """:meth:`submit` from any thread; :meth:`due` in the control thread gives the items due at a
    tick (``at_tick`` None or reached), in arrival order, and those for a tick at or past
    :attr:`end_tick` (the run never reaches it: they are to be refused); :meth:`drain` the
    ones still waiting when the run ends."""

    end_tick: int | None = None
    """The first tick the run will not reach (None: no planned end)."""
    _inbox: queue.SimpleQueue = field(default_factory=queue.SimpleQueue, repr=False)
    _waiting: list[T] = field(default_factory=list, repr=False)

    def submit(self, item: T) -> None:
        """Queue ``item`` (thread-safe; never blocks)."""
        self._inbox.put(item)

    def due(self, tick: int) -> list[T]:
        """The items due at ``tick`` or never reached; the others wait. Control thread only."""
        self._collect()
        if not self._waiting:
            return []
        end = self.end_tick
        now = [
            r
            for r in self._waiting
            if r.at_tick is None or r.at_tick <= tick or (end is not None and r.at_tick >= end)
        ]
        if now:
            self._waiting = [r for r in self._waiting if r not in now]
        return now

    def drain(self) -> list[T]:
        """Every item still waiting (the run ended before its tick). Control thread only."""
        self._collect()
        out, self._waiting = self._waiting, []
        return out

    def _collect(self) -> None:
        """Move the items submitted so far to the waiting list."""
        while not self._inbox.empty():  # no exception raised on the usual empty tick
            try:
                self._waiting.append(self._inbox.get_nowait())
            except queue.Empty:
                break


def beyond_end(at_tick: int, end_tick: int | None) -> str:
    """Why a request for ``at_tick`` is refused before the run ends."""
    return (
        f"tick {at_tick} is beyond the run's end: it plans {end_tick} ticks "
        f"(0..{(end_tick or 0) - 1}), so the request would never be applied"
    )


def run_ended(at_tick: int | None, tick: int | None) -> str:
    """Why a request still waiting at the run's end (last tick ``tick``, None: no tick ran)
    was not applied."""
    when = "before its first tick" if tick is None else f"at tick {tick}"
    return f"not applied: the run ended {when}, before tick {at_tick}"


__all__ = ["DueQueue", "beyond_end", "run_ended"]
