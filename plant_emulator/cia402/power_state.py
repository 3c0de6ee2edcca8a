"""The CiA 402 power state machine of one drive: controlword 0x6040 in, statusword 0x6041 out.

Pure logic, no bus: :class:`~plant_emulator.cia402.drive.EmulatedDrive` feeds it the
controlwords (from the RPDO latched at a SYNC, or an SDO write), the faults its monitors detect,
and one :meth:`PowerStateMachine.tick` per SYNC. Torque is allowed only in OPERATION ENABLED.

The transitions are the profile's numbered ones (IEC 61800-7-201 / CiA 402 part 2):
2 shutdown, 3 switch on, 4 enable operation (3 + 4 in one command from READY TO SWITCH ON),
5 disable operation, 6 and 8 shutdown, 7 / 9 / 10 / 12 disable voltage (and quick stop below
OPERATION ENABLED), 11 quick stop, 13 + 14 fault (the fault reaction, torque off, is immediate),
15 fault reset on the rising edge of bit 7, 16 enable operation out of QUICK STOP ACTIVE (quick
stop option codes 5..8). After a quick stop with option code 0..4 the drive stops (torque off at
once in torque mode) and goes on to SWITCH ON DISABLED: at once for 0, at the next SYNC for 1..4.
"""

from __future__ import annotations

import enum
from collections.abc import Callable


class PowerState(enum.Enum):
    """The states; the value is the statusword's state bits (0-3, 5, 6) and bit 4 (voltage)."""

    NOT_READY_TO_SWITCH_ON = 0x00
    SWITCH_ON_DISABLED = 0x40
    READY_TO_SWITCH_ON = 0x31
    SWITCHED_ON = 0x33
    OPERATION_ENABLED = 0x37
    QUICK_STOP_ACTIVE = 0x17
    FAULT_REACTION_ACTIVE = 0x1F
    FAULT = 0x08


REMOTE = 1 << 9
"""Statusword bit 9: the drive follows the controlword from the network."""
TARGET_VALUE_USED = 1 << 12
"""Statusword bit 12 in cyclic synchronous modes: the drive follows the target value."""
FAULT_RESET = 1 << 7
"""Controlword bit 7: fault reset (acts on its rising edge)."""


class Command(enum.Enum):
    """The device control commands a controlword encodes (bit 7 clear)."""

    DISABLE_VOLTAGE = "disable voltage"
    QUICK_STOP = "quick stop"
    SHUTDOWN = "shutdown"
    SWITCH_ON = "switch on"  # also "disable operation" out of OPERATION ENABLED
    ENABLE_OPERATION = "enable operation"  # "switch on + enable operation"


def decode(controlword: int) -> Command | None:
    """The command of a controlword (bits 0-3, 7); None when bit 7 is set or bits say nothing."""
    cw = controlword & 0x8F
    if cw & 0x80:
        return None
    if cw & 0x02 == 0:
        return Command.DISABLE_VOLTAGE
    if cw & 0x04 == 0:
        return Command.QUICK_STOP
    if cw & 0x01 == 0:
        return Command.SHUTDOWN
    return Command.ENABLE_OPERATION if cw & 0x08 else Command.SWITCH_ON


S = PowerState
_TRANSITIONS: dict[tuple[PowerState, Command], PowerState] = {
    (S.SWITCH_ON_DISABLED, Command.SHUTDOWN): S.READY_TO_SWITCH_ON,  # 2
    (S.READY_TO_SWITCH_ON, Command.SWITCH_ON): S.SWITCHED_ON,  # 3
    (S.READY_TO_SWITCH_ON, Command.ENABLE_OPERATION): S.OPERATION_ENABLED,  # 3 + 4
    (S.READY_TO_SWITCH_ON, Command.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 7
    (S.READY_TO_SWITCH_ON, Command.QUICK_STOP): S.SWITCH_ON_DISABLED,  # 7
    (S.SWITCHED_ON, Command.ENABLE_OPERATION): S.OPERATION_ENABLED,  # 4
    (S.SWITCHED_ON, Command.SHUTDOWN): S.READY_TO_SWITCH_ON,  # 6
    (S.SWITCHED_ON, Command.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 10
    (S.SWITCHED_ON, Command.QUICK_STOP): S.SWITCH_ON_DISABLED,  # 10
    (S.OPERATION_ENABLED, Command.SWITCH_ON): S.SWITCHED_ON,  # 5
    (S.OPERATION_ENABLED, Command.SHUTDOWN): S.READY_TO_SWITCH_ON,  # 8
    (S.OPERATION_ENABLED, Command.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 9
    (S.OPERATION_ENABLED, Command.QUICK_STOP): S.QUICK_STOP_ACTIVE,  # 11
    (S.QUICK_STOP_ACTIVE, Command.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 12
}
_STAY_IN_QUICK_STOP = range(5, 9)
"""Quick stop option codes 5..8: the drive stays in QUICK STOP ACTIVE (transition 16 allowed)."""


class PowerStateMachine:
    """One drive's power state, its last fault and the controlword's bit-7 edge.

    ``quick_stop_option`` reads 0x605A when a quick stop happens; ``enable_check`` is asked
    before operation is enabled and returns an EMCY code that refuses it (the drive faults with
    it) or None."""

    def __init__(
        self,
        quick_stop_option: Callable[[], int] = lambda: 6,
        enable_check: Callable[[], int | None] = lambda: None,
    ) -> None:
        self._quick_stop_option = quick_stop_option
        self._enable_check = enable_check
        self.state = PowerState.NOT_READY_TO_SWITCH_ON
        self.error_code = 0
        """The EMCY code of the active fault (0x603F); 0 when none."""
        self._last_controlword = 0
        self._leave_quick_stop = False
        self.state = PowerState.SWITCH_ON_DISABLED  # transitions 0 and 1: self-test passed

    @property
    def torque_enabled(self) -> bool:
        return self.state is PowerState.OPERATION_ENABLED

    @property
    def faulted(self) -> bool:
        return self.state in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE)

    def statusword(self, *, target_used: bool = False) -> int:
        """0x6041: the state bits, remote, and bit 12 while the target torque is followed."""
        word = self.state.value | REMOTE
        if target_used and self.torque_enabled:
            word |= TARGET_VALUE_USED
        return word

    def controlword(self, word: int) -> PowerState:
        """Apply one controlword; returns the state after it."""
        rising = bool(word & FAULT_RESET) and not self._last_controlword & FAULT_RESET
        self._last_controlword = word
        if self.faulted:
            if rising and self.state is PowerState.FAULT:
                self.state = PowerState.SWITCH_ON_DISABLED  # 15
                self.error_code = 0
            return self.state
        command = decode(word)
        if command is None:
            return self.state
        if self.state is PowerState.QUICK_STOP_ACTIVE and command is Command.ENABLE_OPERATION:
            if not self._leave_quick_stop:
                self._enable(PowerState.OPERATION_ENABLED)  # 16
            return self.state
        target = _TRANSITIONS.get((self.state, command))
        if target is PowerState.OPERATION_ENABLED:
            self._enable(target)
        elif target is PowerState.QUICK_STOP_ACTIVE:
            self._quick_stop()
        elif target is not None:
            self.state = target
        return self.state

    def tick(self) -> None:
        """Once per SYNC: a quick stop with option code 1..4 has stopped; go on (transition 12)."""
        if self.state is PowerState.QUICK_STOP_ACTIVE and self._leave_quick_stop:
            self.state = PowerState.SWITCH_ON_DISABLED
            self._leave_quick_stop = False

    def fault(self, code: int) -> bool:
        """A fault (transitions 13 and 14): torque off, FAULT; True if the drive was not already
        faulted (the caller then sends the EMCY). A fault in FAULT keeps the first code."""
        if self.faulted:
            return False
        self.state = PowerState.FAULT_REACTION_ACTIVE  # 13: torque off (immediate in torque mode)
        self.error_code = code
        self._leave_quick_stop = False
        self.state = PowerState.FAULT  # 14
        return True

    def _enable(self, target: PowerState) -> None:
        refused = self._enable_check()
        if refused is not None:
            self.fault(refused)
        else:
            self.state = target

    def _quick_stop(self) -> None:
        option = self._quick_stop_option()
        if option == 0:
            self.state = PowerState.SWITCH_ON_DISABLED
        else:
            self.state = PowerState.QUICK_STOP_ACTIVE
            self._leave_quick_stop = option not in _STAY_IN_QUICK_STOP
