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
    tick (``at_tick`` None or reached), in arrival order."""

    _inbox: queue.SimpleQueue = field(default_factory=queue.SimpleQueue, repr=False)
    _waiting: list[T] = field(default_factory=list, repr=False)

    def submit(self, item: T) -> None:
        """Queue ``item`` (thread-safe; never blocks)."""
        self._inbox.put(item)

    def due(self, tick: int) -> list[T]:
        """The items due at ``tick``; the others wait. Control thread only."""
        while not self._inbox.empty():  # no exception raised on the usual empty tick
            try:
                self._waiting.append(self._inbox.get_nowait())
            except queue.Empty:
                break
        if not self._waiting:
            return []
        now = [r for r in self._waiting if r.at_tick is None or r.at_tick <= tick]
        if now:
            self._waiting = [r for r in self._waiting if r not in now]
        return now


__all__ = ["DueQueue"]
