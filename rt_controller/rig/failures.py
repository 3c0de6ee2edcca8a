"""How a rig run fails: a process that died or would not start, a controller that hung past its
wall-clock budget, a cancelled run (``hil up``, ``hil experiment``, the sweep's rig engine)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from rt_controller.errors import ControllerError
from rt_controller.rig.ending import ProcessEnd


class RigProcessError(ControllerError, RuntimeError):
    """A rig process failed; the message carries its exit status and stderr tail."""


class RigProcessDied(RigProcessError):
    """A process of the rig ended while the run went on (``end`` says which, how and when)."""

    def __init__(self, end: ProcessEnd, tail: str) -> None:
        self.end = end
        super().__init__(with_tail(f"{end.name} {end.how}", tail))


class RigHung(RigProcessError):
    """The controller was still running after its wall-clock budget; the rig was stopped.
    ``summary`` is what the controller reported when stopped (None if it reported nothing)."""

    summary: dict[str, Any] | None = None


def with_tail(message: str, tail: str) -> str:
    """``message``, then a child's stderr tail on the lines below when it has one."""
    return f"{message}:\n{tail}" if tail else message


class RigCancelled(ControllerError):
    """The run was cancelled (:attr:`RigOptions.cancel`) before it ended; its processes have
    been stopped."""

    summaries: Sequence[dict[str, Any]] = ()
    """Of a plan (:func:`~rt_controller.rig.processes.run_rig_plan`): the summaries of its
    runs that ended before the cancel, which keep their results."""
