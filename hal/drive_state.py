"""Drive state machine of the rig's DSP, modelled on CiA 402 (pure: no I/O, no clock).

Both ends of the CAN link share these names: the DSP (``plant_emulator.dsp_node``) runs a
:class:`Drive`, reports ``DriveState``, ``FaultReason`` and a per-process ``Session`` in
``DspStatus``, and the controller follows it with a :class:`DriveMonitor`.

States (``DspStatus.DriveState``)::

    NOT_READY (0) --boot--> SWITCH_ON_DISABLED (1) --DISABLE--> READY_TO_SWITCH_ON (2)
    SWITCH_ON_DISABLED / READY_TO_SWITCH_ON --ENABLE--> OPERATION_ENABLED (3)
    OPERATION_ENABLED --DISABLE--> READY_TO_SWITCH_ON
    any non-fault state --DISABLE_VOLTAGE--> SWITCH_ON_DISABLED
    any state --fault(reason)--> FAULT (4), torque off at once
    FAULT --FAULT_RESET--> SWITCH_ON_DISABLED (then ENABLE again)

Torque reaches the arm only in ``OPERATION_ENABLED``. In ``FAULT`` every command except
``FAULT_RESET`` is refused (counted); the first fault's reason is kept until the reset.
``ENABLE`` collapses CiA 402's shutdown / switch on / enable operation into one command (the
DSP has no separate power stage), and ``DISABLE`` is CiA's *shutdown* (ready, torque off).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Protocol


class DriveState(enum.IntEnum):
    """Values of ``DspStatus.DriveState`` (3 bits)."""

    NOT_READY = 0
    """Booting; never reported once the DSP runs."""
    SWITCH_ON_DISABLED = 1
    """After boot and after a fault reset: torque off, ENABLE arms."""
    READY_TO_SWITCH_ON = 2
    """After DISABLE: torque off, ENABLE arms."""
    OPERATION_ENABLED = 3
    """Torque commands are applied (subject to the watchdog and the limits)."""
    FAULT = 4
    """Torque off until FAULT_RESET; ``DspStatus.FaultReason`` says why."""

    @property
    def label(self) -> str:
        return self.name.lower()


class FaultReason(enum.IntEnum):
    """Values of ``DspStatus.FaultReason`` (4 bits): why the DSP entered FAULT."""

    NONE = 0
    WATCHDOG = 1
    """No valid TorqueCommand for ``dsp.watchdog_periods`` control periods."""
    POSITION_LIMIT = 2
    """A joint angle left ``[dsp.q_min, dsp.q_max]`` while operation was enabled."""
    VELOCITY_LIMIT = 3
    """A joint speed exceeded ``dsp.dq_max`` while operation was enabled."""
    ENCODER = 4
    """A joint angle or velocity the CAN frame cannot carry (beyond +-8 rev / +-83.9 rad/s):
    the DSP stops sending joint state rather than report a pinned value."""

    @property
    def label(self) -> str:
        return self.name.lower()


class DspCommand(enum.IntEnum):
    """Values of ``DspControl.Command``; any other value is a decode error."""

    ENABLE = 1
    """SWITCH_ON_DISABLED / READY_TO_SWITCH_ON -> OPERATION_ENABLED (refused in FAULT)."""
    DISABLE = 2
    """-> READY_TO_SWITCH_ON (torque off); refused in FAULT."""
    FAULT_RESET = 3
    """FAULT -> SWITCH_ON_DISABLED; no effect in other states."""
    DISABLE_VOLTAGE = 4
    """-> SWITCH_ON_DISABLED (torque off); refused in FAULT."""


_ARMABLE = (DriveState.SWITCH_ON_DISABLED, DriveState.READY_TO_SWITCH_ON)


def next_state(state: DriveState, command: DspCommand) -> DriveState | None:
    """The state after ``command`` in ``state``; ``None`` when the command is refused there.

    A command that leaves the state as it is (e.g. ENABLE while enabled, FAULT_RESET with no
    fault) returns ``state``, not ``None``.
    """
    if state is DriveState.FAULT:
        return DriveState.SWITCH_ON_DISABLED if command is DspCommand.FAULT_RESET else None
    if state is DriveState.NOT_READY:
        return None
    if command is DspCommand.ENABLE:
        return DriveState.OPERATION_ENABLED
    if command is DspCommand.DISABLE:
        return DriveState.READY_TO_SWITCH_ON
    if command is DspCommand.DISABLE_VOLTAGE:
        return DriveState.SWITCH_ON_DISABLED
    return state  # FAULT_RESET outside FAULT


@dataclass
class Drive:
    """The DSP's state machine: current state, fault reason and counters."""

    state: DriveState = DriveState.SWITCH_ON_DISABLED
    fault_reason: FaultReason = FaultReason.NONE
    faults: dict[str, int] = field(default_factory=dict)
    """Faults entered, by reason label (``watchdog``, ``position_limit``, ...)."""
    refused: int = 0
    """Commands refused in the current state (e.g. ENABLE in FAULT)."""

    @property
    def torque_allowed(self) -> bool:
        return self.state is DriveState.OPERATION_ENABLED

    def command(self, command: DspCommand) -> bool:
        """Apply ``command``; whether it was accepted (refusals are counted)."""
        new = next_state(self.state, DspCommand(command))
        if new is None:
            self.refused += 1
            return False
        if self.state is DriveState.FAULT:
            self.fault_reason = FaultReason.NONE
        self.state = new
        return True

    def fault(self, reason: FaultReason) -> bool:
        """Enter FAULT for ``reason``; False (nothing changes) when already in FAULT."""
        if self.state is DriveState.FAULT:
            return False
        self.state = DriveState.FAULT
        self.fault_reason = FaultReason(reason)
        label = self.fault_reason.label
        self.faults[label] = self.faults.get(label, 0) + 1
        return True


# ---------------------------------------------------------------------- controller side


class StatusLike(Protocol):
    """What :class:`DriveMonitor` reads of a ``hal.can_frames.DspStatus``."""

    @property
    def drive_state(self) -> DriveState: ...
    @property
    def fault_reason(self) -> FaultReason: ...
    @property
    def session(self) -> int: ...


MODE_ENABLED = "enabled"
"""The DSP reports OPERATION_ENABLED and no restart is pending: a law may run."""
MODE_DISARMED = "disarmed"
"""SWITCH_ON_DISABLED, READY_TO_SWITCH_ON or NOT_READY: zero torque."""
MODE_FAULT = "fault"
"""The DSP reports FAULT (see :attr:`DriveUpdate.fault`)."""
MODE_DSP_RESTARTED = "dsp_restarted"
"""The DSP's session changed since the first status; latched until
:meth:`DriveMonitor.acknowledge_restart`."""
MODE_NO_STATUS = "no_status"
"""No DspStatus received yet."""
MODES = (MODE_ENABLED, MODE_DISARMED, MODE_FAULT, MODE_DSP_RESTARTED, MODE_NO_STATUS)


class DriveEvent(enum.Enum):
    """What :meth:`DriveMonitor.update` noticed in one status."""

    FIRST_STATUS = "first_status"
    STATE_CHANGED = "state_changed"
    DSP_RESTARTED = "dsp_restarted"
    """The session id changed: a new DSP process (its state machine started over)."""
    FAULT = "fault"
    """The DSP entered FAULT (reason in :attr:`DriveUpdate.fault`)."""
    FAULT_CLEARED = "fault_cleared"
    DISARMED = "disarmed"
    """OPERATION_ENABLED was left for a non-fault state (e.g. a DISABLE from anywhere)."""
    ENABLED = "enabled"


@dataclass(frozen=True)
class DriveUpdate:
    """Result of one :meth:`DriveMonitor.update`."""

    mode: str
    """One of :data:`MODES`; a control law runs only in :data:`MODE_ENABLED`."""
    state: DriveState | None
    fault: FaultReason
    events: tuple[DriveEvent, ...] = ()

    @property
    def may_apply_torque(self) -> bool:
        return self.mode == MODE_ENABLED


class DriveMonitor:
    """Controller-side tracker of the DSP's drive state (pure: feed it every status you read).

    ``update(status)`` with the latest ``DspStatus`` (or ``None`` before the first one) returns
    the mode for this tick and the events since the previous call. Feeding the same status
    object twice yields no events. A session change is a DSP restart: the mode is
    ``dsp_restarted`` until :meth:`acknowledge_restart` (the re-arm policy is the caller's).
    :meth:`counters` counts events by name and faults by reason (``fault.<reason>``).
    """

    def __init__(self) -> None:
        self.session: int | None = None
        self.state: DriveState | None = None
        self.fault: FaultReason = FaultReason.NONE
        self.restart_pending = False
        self._last: object = None
        self._counts: dict[str, int] = {}

    def _count(self, key: str) -> None:
        self._counts[key] = self._counts.get(key, 0) + 1

    def acknowledge_restart(self) -> None:
        """Accept the new DSP session (the mode follows its state again)."""
        self.restart_pending = False

    def _mode(self) -> str:
        if self.state is None:
            return MODE_NO_STATUS
        if self.restart_pending:
            return MODE_DSP_RESTARTED
        if self.state is DriveState.FAULT:
            return MODE_FAULT
        if self.state is DriveState.OPERATION_ENABLED:
            return MODE_ENABLED
        return MODE_DISARMED

    @property
    def mode(self) -> str:
        return self._mode()

    def update(self, status: StatusLike | None) -> DriveUpdate:
        if status is None or status is self._last:
            return DriveUpdate(self._mode(), self.state, self.fault)
        self._last = status
        events: list[DriveEvent] = []
        state, reason, session = status.drive_state, status.fault_reason, status.session
        if self.session is None:
            events.append(DriveEvent.FIRST_STATUS)
        elif session != self.session:
            events.append(DriveEvent.DSP_RESTARTED)
            self.restart_pending = True
        if self.state is not None and state is not self.state:
            events.append(DriveEvent.STATE_CHANGED)
            if state is DriveState.OPERATION_ENABLED:
                events.append(DriveEvent.ENABLED)
            elif self.state is DriveState.OPERATION_ENABLED and state is not DriveState.FAULT:
                events.append(DriveEvent.DISARMED)
            if self.state is DriveState.FAULT:
                events.append(DriveEvent.FAULT_CLEARED)
        new_fault = state is DriveState.FAULT and (
            self.state is not DriveState.FAULT or DriveEvent.DSP_RESTARTED in events
        )
        if new_fault:
            events.append(DriveEvent.FAULT)
            self._count(f"fault.{FaultReason(reason).label}")
        self.session, self.state = session, state
        self.fault = reason if state is DriveState.FAULT else FaultReason.NONE
        for ev in events:
            self._count(ev.value)
        return DriveUpdate(self._mode(), state, self.fault, tuple(events))

    def as_dict(self) -> dict[str, int]:
        """Events by name (``dsp_restarted``, ``fault``, ``disarmed``, ...) and faults by
        reason (``fault.watchdog``, ``fault.position_limit``, ...)."""
        return dict(self._counts)


__all__ = [
    "MODES",
    "MODE_DISARMED",
    "MODE_DSP_RESTARTED",
    "MODE_ENABLED",
    "MODE_FAULT",
    "MODE_NO_STATUS",
    "Drive",
    "DriveEvent",
    "DriveMonitor",
    "DriveState",
    "DriveUpdate",
    "DspCommand",
    "FaultReason",
    "next_state",
]
