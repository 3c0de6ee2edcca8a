"""A python-can bus that shows every frame it sends and receives to hooks: how the run's log
sees the raw frames of either hardware profile. The DSP client
(:class:`~hal.joint_client.JointClient`) reads and writes its bus through one, and so does a
CANopen master (canopen's :class:`~canopen.Network`, which owns its bus).

The hooks run where the frame passes: ``tx_hook`` on the sender's thread just before the
frame goes out, ``rx_hook`` on the receive thread (the control loop's, or canopen's notifier)
as it comes in, before any check. A hook that raises is counted in
:attr:`FrameTap.hook_errors` and never stops the frame (the run counts such a frame as a lost
log record). Frames that python-can sends by itself (``send_periodic``, the controller's
heartbeat) do not pass here.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import can

Hook = Callable[[can.Message], Any]


class FrameTap:
    """``bus`` with :attr:`rx_hook` and :attr:`tx_hook` (None: off); everything else is the
    bus's own (attribute access is forwarded)."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.rx_hook: Hook | None = None
        self.tx_hook: Hook | None = None
        self.hook_errors = 0

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if (hook := self.tx_hook) is not None:
            self._show(hook, msg)
        self.bus.send(msg, timeout)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        msg = self.bus.recv(timeout)
        if msg is not None and (hook := self.rx_hook) is not None:
            self._show(hook, msg)
        return msg

    def _show(self, hook: Hook, msg: can.Message) -> None:
        try:
            hook(msg)
        except Exception:  # the log never stops a frame
            self.hook_errors += 1

    def __getattr__(self, name: str) -> Any:
        return getattr(self.bus, name)


__all__ = ["FrameTap"]
