"""The typed CAN frames of the HIL rig (:class:`TorqueCommand`, :class:`DspControl`,
:class:`JointPosition`, :class:`JointVelocity`, :class:`DspStatus`, :class:`Sync`), the joint
state the controller assembles from them, and each frame's signal values in ``hal/hil.dbc``
(:data:`TO_SIGNALS`, :data:`FROM_SIGNALS`). Encoding them is :mod:`hal.can_codec`'s."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from hal.drive_state import DriveState, DspCommand, FaultReason

STRICT_SIGNALS = frozenset({"Q1", "Q2", "Dq1", "Dq2"})
"""Measurements that are never saturated on encode: a value beyond the signal's range raises
:class:`~hal.errors.HalCodecError` (a pinned joint angle or speed would lie to the controller;
the DSP faults with FaultReason ENCODER instead)."""

ENCODER_COUNTS_PER_REV = 1 << 20
RAD_PER_COUNT = 2.0 * math.pi / ENCODER_COUNTS_PER_REV
"""Resolution of the joint-angle signals Q1/Q2 (20-bit direct-drive encoder)."""
RELEASE_DELAY_SATURATED = 0xFFFF
"""Realtime ``TorqueCommand.Tick``: microseconds from the controller's release to the frame;
this value means "this long or more" (the DSP then does not learn the phase from it)."""


@dataclass(frozen=True, slots=True)
class TorqueCommand:
    """Controller -> DSP torque command (N·m). ``tick``: in lockstep the Sync period it answers
    (low 16 bits); in realtime the microseconds from the controller's release to this frame
    (:data:`RELEASE_DELAY_SATURATED` and above saturate)."""

    tau1: float
    tau2: float
    enable: bool = True
    tick: int = 0


@dataclass(frozen=True, slots=True)
class DspControl:
    """Controller -> DSP event command (the drive state machine, :mod:`hal.drive_state`)."""

    command: DspCommand


@dataclass(frozen=True, slots=True)
class JointPosition:
    """DSP -> controller joint angles (rad); ``sample`` is the DSP sample index mod 16."""

    q1: float
    q2: float
    sample: int = 0


@dataclass(frozen=True, slots=True)
class JointVelocity:
    """DSP -> controller joint velocities (rad/s); ``sample`` pairs it with a JointPosition."""

    dq1: float
    dq2: float
    sample: int = 0


@dataclass(frozen=True, slots=True)
class DspStatus:
    """DSP -> controller status flags, counters and drive state (see :mod:`hal.drive_state`).

    ``drive_state`` / ``fault_reason`` default to what the legacy flags imply (TorqueEnabled ->
    OPERATION_ENABLED, WatchdogTripped -> FAULT/WATCHDOG, else SWITCH_ON_DISABLED), so a status
    built from the flags alone round-trips. ``session`` is the DSP process's random id (0 =
    unknown); ``tick`` is carried mod 4096, ``watchdog_trips`` saturates at 15.
    """

    torque_enabled: bool
    watchdog_tripped: bool
    torque_saturated: bool = False
    lockstep: bool = False
    rejected_frames: int = 0
    watchdog_trips: int = 0
    tick: int = 0
    drive_state: DriveState | None = None
    fault_reason: FaultReason | None = None
    session: int = 0

    def __post_init__(self) -> None:
        state = self.drive_state
        if state is None:
            if self.watchdog_tripped:
                state = DriveState.FAULT
            elif self.torque_enabled:
                state = DriveState.OPERATION_ENABLED
            else:
                state = DriveState.SWITCH_ON_DISABLED
        object.__setattr__(self, "drive_state", DriveState(state))
        reason = self.fault_reason
        if reason is None:
            reason = (
                FaultReason.WATCHDOG
                if self.watchdog_tripped and state is DriveState.FAULT
                else FaultReason.NONE
            )
        object.__setattr__(self, "fault_reason", FaultReason(reason))

    @property
    def fault(self) -> bool:
        return self.drive_state is DriveState.FAULT


@dataclass(frozen=True, slots=True)
class Sync:
    """DSP -> controller lockstep clock: control period index ``tick``."""

    tick: int


@dataclass(frozen=True, slots=True)
class JointState:
    """One DSP sample of both joints, as the controller sees it.

    ``t_ns`` is the ``time.monotonic_ns()`` at which the second frame of the pair arrived.
    """

    q: tuple[float, float]
    dq: tuple[float, float]
    sample: int
    t_ns: int

    def age_s(self, now_ns: int | None = None) -> float:
        """Seconds since this state was received."""
        now = time.monotonic_ns() if now_ns is None else now_ns
        return (now - self.t_ns) * 1e-9


Frame = TorqueCommand | DspControl | JointPosition | JointVelocity | DspStatus | Sync


# ------------------------------------------------------------------- dataclass <-> signals


def _sat(value: int, limit: int) -> int:
    return max(0, min(int(value), limit))


def _control_signals(f: DspControl) -> dict[str, Any]:
    return {"Command": int(f.command)}


def _control_from(s: dict[str, Any]) -> DspControl:
    return DspControl(DspCommand(s["Command"]))


TO_SIGNALS: dict[type, tuple[str, Callable[[Any], dict[str, Any]]]] = {
    TorqueCommand: (
        "TorqueCommand",
        lambda f: {
            "Enable": int(bool(f.enable)),
            "Tau1": f.tau1,
            "Tau2": f.tau2,
            "Tick": int(f.tick) & 0xFFFF,
        },
    ),
    DspControl: ("DspControl", lambda f: _control_signals(f)),
    JointPosition: (
        "JointPosition",
        lambda f: {"Sample": int(f.sample) & 0xF, "Q1": f.q1, "Q2": f.q2},
    ),
    JointVelocity: (
        "JointVelocity",
        lambda f: {"Sample": int(f.sample) & 0xF, "Dq1": f.dq1, "Dq2": f.dq2},
    ),
    DspStatus: (
        "DspStatus",
        lambda f: {
            "TorqueEnabled": int(bool(f.torque_enabled)),
            "WatchdogTripped": int(bool(f.watchdog_tripped)),
            "TorqueSaturated": int(bool(f.torque_saturated)),
            "Lockstep": int(bool(f.lockstep)),
            "RejectedFrames": _sat(f.rejected_frames, 255),
            "DriveState": int(f.drive_state),
            "FaultReason": int(f.fault_reason),
            "Session": int(f.session) & 0xFFFF,
            "WatchdogTrips": _sat(f.watchdog_trips, 15),
            "Tick": int(f.tick) & 0xFFF,
        },
    ),
    Sync: ("Sync", lambda f: {"Tick": int(f.tick) & 0xFFFFFFFF}),
}

FROM_SIGNALS: dict[str, Callable[[dict[str, Any]], Frame]] = {
    "TorqueCommand": lambda s: TorqueCommand(s["Tau1"], s["Tau2"], bool(s["Enable"]), s["Tick"]),
    "DspControl": lambda s: _control_from(s),
    "JointPosition": lambda s: JointPosition(s["Q1"], s["Q2"], s["Sample"]),
    "JointVelocity": lambda s: JointVelocity(s["Dq1"], s["Dq2"], s["Sample"]),
    "DspStatus": lambda s: DspStatus(
        bool(s["TorqueEnabled"]),
        bool(s["WatchdogTripped"]),
        bool(s["TorqueSaturated"]),
        bool(s["Lockstep"]),
        s["RejectedFrames"],
        s["WatchdogTrips"],
        s["Tick"],
        DriveState(s["DriveState"]),
        FaultReason(s["FaultReason"]),
        s["Session"],
    ),
    "Sync": lambda s: Sync(s["Tick"]),
}
