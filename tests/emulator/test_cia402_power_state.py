"""The CiA 402 power state machine: the whole transition table, quick stop, fault and reset."""

from __future__ import annotations

import pytest

from plant_emulator.cia402.power_state import PowerState, PowerStateMachine

S = PowerState
SHUTDOWN, SWITCH_ON, ENABLE, DISABLE_VOLTAGE, QUICK_STOP, FAULT_RESET = 0x06, 0x07, 0x0F, 0, 2, 0x80


def enabled(option: int = 6) -> PowerStateMachine:
    m = PowerStateMachine(quick_stop_option=lambda: option)
    for word in (SHUTDOWN, SWITCH_ON, ENABLE):
        m.controlword(word)
    assert m.state is S.OPERATION_ENABLED
    return m


def test_power_up_path_to_operation_enabled_and_the_statuswords():
    m = PowerStateMachine()
    assert m.state is S.SWITCH_ON_DISABLED
    seen = [m.statusword() & 0x6F]
    for word in (SHUTDOWN, SWITCH_ON, ENABLE):
        m.controlword(word)
        seen.append(m.statusword() & 0x6F)
    # canopen BaseNode402's masks: SOD 0x40/0x4F, RTSO 0x21, SO 0x23, OE 0x27 (0x6F)
    assert [seen[0] & 0x4F, *seen[1:]] == [0x40, 0x21, 0x23, 0x27]
    assert m.torque_enabled
    assert m.statusword() & 0x200  # remote
    assert m.statusword(target_used=True) & 0x1000


def test_switch_on_and_enable_in_one_command_from_ready_to_switch_on():
    m = PowerStateMachine()
    m.controlword(SHUTDOWN)
    assert m.controlword(ENABLE) is S.OPERATION_ENABLED


@pytest.mark.parametrize(
    ("word", "state"),
    [
        (SWITCH_ON, S.SWITCHED_ON),  # 5 disable operation
        (SHUTDOWN, S.READY_TO_SWITCH_ON),  # 8
        (DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED),  # 9
    ],
)
def test_leaving_operation_enabled_takes_the_torque_off(word, state):
    m = enabled()
    assert m.controlword(word) is state
    assert not m.torque_enabled


def test_torque_only_in_operation_enabled():
    m = PowerStateMachine()
    states = []
    for word in (SHUTDOWN, SWITCH_ON, ENABLE, QUICK_STOP):
        m.controlword(word)
        states.append((m.state, m.torque_enabled))
    assert [s for s, on in states if on] == [S.OPERATION_ENABLED]


def test_quick_stop_option_6_stays_in_quick_stop_and_can_return_to_operation():
    m = enabled(option=6)
    assert m.controlword(QUICK_STOP) is S.QUICK_STOP_ACTIVE
    assert not m.torque_enabled
    assert m.statusword() & 0x6F == 0x07  # BaseNode402: QUICK STOP ACTIVE
    m.tick()
    assert m.state is S.QUICK_STOP_ACTIVE
    assert m.controlword(ENABLE) is S.OPERATION_ENABLED  # 16


def test_quick_stop_option_2_goes_on_to_switch_on_disabled_at_the_next_sync():
    m = enabled(option=2)
    assert m.controlword(QUICK_STOP) is S.QUICK_STOP_ACTIVE
    assert m.controlword(ENABLE) is S.QUICK_STOP_ACTIVE  # no 16 for option 1..4
    m.tick()
    assert m.state is S.SWITCH_ON_DISABLED


def test_quick_stop_option_0_disables_at_once():
    m = enabled(option=0)
    assert m.controlword(QUICK_STOP) is S.SWITCH_ON_DISABLED


def test_quick_stop_then_disable_voltage_is_transition_12():
    m = enabled(option=6)
    m.controlword(QUICK_STOP)
    assert m.controlword(DISABLE_VOLTAGE) is S.SWITCH_ON_DISABLED


@pytest.mark.parametrize("word", [QUICK_STOP, DISABLE_VOLTAGE])
def test_quick_stop_and_disable_voltage_below_operation(word):
    m = PowerStateMachine()
    m.controlword(SHUTDOWN)
    m.controlword(SWITCH_ON)
    assert m.controlword(word) is S.SWITCH_ON_DISABLED  # 10


def test_fault_takes_torque_off_and_only_a_rising_edge_of_bit_7_leaves_it():
    m = enabled()
    assert m.fault(0x8700)
    assert m.state is S.FAULT and not m.torque_enabled
    assert m.statusword() & 0x4F == 0x08
    assert m.error_code == 0x8700
    for word in (SHUTDOWN, SWITCH_ON, ENABLE, QUICK_STOP, DISABLE_VOLTAGE):
        assert m.controlword(word) is S.FAULT  # no command leaves FAULT
    m.tick()
    assert m.state is S.FAULT  # nor time
    assert m.controlword(FAULT_RESET) is S.SWITCH_ON_DISABLED  # 15
    assert m.error_code == 0


def test_fault_reset_needs_an_edge_not_a_level():
    m = enabled()
    m.controlword(FAULT_RESET | SHUTDOWN)  # bit 7 high before the fault: ignored outside FAULT
    assert m.state is S.OPERATION_ENABLED
    m.fault(0x8130)
    assert m.controlword(FAULT_RESET) is S.FAULT  # bit 7 still high: no rising edge
    m.controlword(0)
    assert m.controlword(FAULT_RESET) is S.SWITCH_ON_DISABLED


def test_a_second_fault_keeps_the_first_code():
    m = enabled()
    assert m.fault(0x8700)
    assert not m.fault(0x8130)
    assert m.error_code == 0x8700


def test_a_refused_enable_is_a_fault():
    m = PowerStateMachine(enable_check=lambda: 0x6320)
    m.controlword(SHUTDOWN)
    m.controlword(SWITCH_ON)
    assert m.controlword(ENABLE) is S.FAULT
    assert m.error_code == 0x6320
