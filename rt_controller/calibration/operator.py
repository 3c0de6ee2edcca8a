"""Operator actions: arm, disarm, a marker in the log, a scenario reset; asked by any front-end
over the same signed link as the parameters, done by the control thread at a tick boundary.

:class:`ActionQueue` takes :class:`Action` objects from any thread (:meth:`ActionQueue.submit`);
the loop takes the due ones at each tick boundary (:meth:`ActionQueue.due`), does them and calls
:meth:`Action.finish`, which answers the asker and gives the ``/controller/events`` record
(:data:`EVENT_SCHEMA`). An action that cannot be done carries its :attr:`Action.refusal`.

Pure: no I/O, no clocks.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rt_controller.calibration.handover import DueQueue, beyond_end, run_ended

ACTIONS: dict[str, str] = {
    "arm": "arm the DSP (FAULT_RESET + ENABLE)",
    "disarm": "disarm the DSP (DISABLE, zero torque); no automatic re-arm until arm",
    "mark": "a marker in the log (/controller/events) with a note",
    "reset_scenario": "restart the scenario (refused in a running controller, see the reason)",
}
"""The actions a running controller knows."""

RESET_REFUSAL = (
    "a scenario reset is not done mid-run: the emulated DSP resets only while disarmed and in "
    "lockstep, and a reset restarts the tick count and the world, so one log would hold two "
    "runs that hil replay cannot repeat; stop and start the run (or use hil controller --plan, "
    "which resets between runs)"
)


def refusal(action: str) -> str | None:
    """Why ``action`` is not done (None when the loop does it)."""
    if action not in ACTIONS:
        return f"unknown action {action!r} (known: {', '.join(ACTIONS)})"
    if action == "reset_scenario":
        return RESET_REFUSAL
    return None


@dataclass
class Action:
    """One operator action; ``reply`` is called once with the event record, in the control
    thread. ``at_tick``: at the first tick >= it (None: the next tick boundary)."""

    action: str
    note: str = ""
    source: str = "unknown"
    at_tick: int | None = None
    request_id: str = ""
    reply: Callable[[dict[str, Any]], Any] | None = None
    invalid: str | None = None
    """Why it is refused whatever it is (a malformed ``at_tick``): at the next boundary."""

    @property
    def refusal(self) -> str | None:
        return self.invalid or refusal(self.action)

    def finish(
        self, tick: int, *, accepted: bool = True, reason: str | None = None, t_ns: int = 0
    ) -> ActionOutcome:
        """What became of it at ``tick``; answers the asker."""
        out = ActionOutcome(
            tick, self.action, accepted, reason, self.note, self.source, self.request_id,
            self.at_tick, t_ns,
        )  # fmt: skip
        if self.reply is not None:
            self.reply(out.record())
        return out


@dataclass
class ActionOutcome:
    """The ``/controller/events`` record of one action (:meth:`record`)."""

    tick: int
    action: str
    accepted: bool
    reason: str | None
    note: str
    source: str
    request_id: str
    at_tick: int | None
    t_ns: int

    def record(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


EVENT_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "hil.OperatorEvent",
    "description": "One operator action (arm, disarm, mark, reset_scenario), done or refused; "
    "the fields after action as in hil.ParameterChange.",
    "type": "object",
    "properties": {
        "action": {"type": "string", "enum": ["arm", "disarm", "mark", "reset_scenario"]},
        "note": {"type": "string", "description": "the operator's note (a mark's text)"},
        "tick": {"type": "integer", "description": "the tick at which it was done or refused"},
        "accepted": {"type": "boolean"},
        "reason": {"type": "string"},
        "t_ns": {"type": "integer"},
        "source": {"type": "string"},
        "request_id": {"type": "string"},
        "at_tick": {"type": "integer"},
    },
    "required": ["tick", "action", "accepted", "source"],
}


class ActionQueue(DueQueue[Action]):
    """The actions' hand-over: :meth:`submit` from any thread, :meth:`due` in the control
    thread (each action due is to be finished)."""

    def refusal(self, act: Action, tick: int) -> str | None:
        """Why ``act``, due at ``tick``, is not done: its own :attr:`Action.refusal`, or its
        tick is past the run's planned end (the only way it is due before its tick)."""
        if act.at_tick is not None and act.at_tick > tick:
            return beyond_end(act.at_tick, self.end_tick)
        return act.refusal

    def end(self, tick: int | None, t_ns: int = 0) -> list[ActionOutcome]:
        """At the run's end (last tick ``tick``; None: none ran, logged as tick 0): the
        actions still waiting, refused as not applied (each answered, the records are for
        the log). Control thread only."""
        return [
            act.finish(tick or 0, accepted=False, reason=run_ended(act.at_tick, tick), t_ns=t_ns)
            for act in self.drain()
        ]


__all__ = [
    "ACTIONS",
    "EVENT_SCHEMA",
    "RESET_REFUSAL",
    "Action",
    "ActionOutcome",
    "ActionQueue",
    "refusal",
]
