"""The cia402 master's pure parts: units from the object dictionary, 0x60C2 from the control
period, and the controlword of each step of the power state machine walk."""

from __future__ import annotations

import math

import pytest

from hal.cia402_master.master import controlword_toward
from hal.cia402_master.units import INT16_MAX, DriveUnits, interpolation_period
from hal.errors import HalConfigError

DIRECT = DriveUnits(1 << 20, 1, 1, 1, 10_000)
"""A 20-bit encoder on a direct drive, 10 N·m rated (the emulated joint 1)."""
GEARED = DriveUnits(4096, 2, 3, 1, 2_000)
"""4096 increments per 2 motor revolutions, 3 motor revolutions per joint revolution, 2 N·m."""


def test_position_and_velocity_from_encoder_and_gear():
    assert DIRECT.position_rad(1 << 20) == pytest.approx(2 * math.pi, rel=1e-12)
    assert DIRECT.velocity_rad_s(-(1 << 19)) == pytest.approx(-math.pi, rel=1e-12)
    # one joint revolution = 3 motor revolutions = 3 * 2048 increments
    assert GEARED.position_rad(3 * 2048) == pytest.approx(2 * math.pi, rel=1e-12)
    assert GEARED.increments_per_rad == pytest.approx(3 * 2048 / (2 * math.pi), rel=1e-12)


def test_torque_is_per_mille_of_rated_torque_at_the_joint():
    assert DIRECT.per_mille(1.0) == 100
    assert DIRECT.torque_nm(-250) == pytest.approx(-2.5)
    # geared: the joint sees 3 x the motor's 2 N·m rated torque
    assert GEARED.joint_rated_torque_nm == pytest.approx(6.0)
    assert GEARED.per_mille(3.0) == 500
    assert GEARED.torque_nm(GEARED.per_mille(1.234)) == pytest.approx(1.234, abs=0.003)


def test_torque_is_clipped_to_the_limit_and_to_int16():
    assert DIRECT.per_mille(200.0, limit_per_mille=15_000) == 15_000
    assert DIRECT.per_mille(-200.0, limit_per_mille=15_000) == -15_000
    assert DIRECT.per_mille(1e6) == INT16_MAX
    assert DIRECT.per_mille(math.nan) == 0
    assert DIRECT.per_mille(-math.inf, limit_per_mille=900) == -900


def test_torque_limit_in_per_mille_rounds_down():
    assert DIRECT.limit_per_mille(150.0) == 15_000
    assert DIRECT.limit_per_mille(0.10009) == 10
    assert DIRECT.limit_per_mille(1e4) == INT16_MAX
    with pytest.raises(HalConfigError):
        DIRECT.limit_per_mille(0.0)


def test_units_must_be_positive():
    with pytest.raises(HalConfigError, match="rated_torque_mnm"):
        DriveUnits(1 << 20, 1, 1, 1, 0)


@pytest.mark.parametrize(
    ("period_s", "pair"),
    [(0.02, (20, -3)), (0.0025, (25, -4)), (0.001, (1, -3)), (1.0, (100, -2)), (0.1, (100, -3))],
)
def test_interpolation_period_is_exact(period_s, pair):
    assert interpolation_period(period_s) == pair
    value, index = pair
    assert value * 10.0**index == pytest.approx(period_s, rel=1e-12)


def test_interpolation_period_refuses_an_inexact_period():
    with pytest.raises(HalConfigError, match="60C2"):
        interpolation_period(1 / 60)


@pytest.mark.parametrize(
    ("statusword", "last", "word"),
    [
        (0x0040, 0x0000, 0x0006),  # switch on disabled -> shutdown (2)
        (0x0021, 0x0006, 0x0007),  # ready to switch on -> switch on (3)
        (0x0023, 0x0007, 0x000F),  # switched on -> enable operation (4)
        (0x0027, 0x000F, 0x000F),  # operation enabled: stay
        (0x0007, 0x0002, 0x000F),  # quick stop active -> enable operation (16)
        (0x0008, 0x000F, 0x0080),  # fault: rising edge of bit 7 (15)
        (0x0008, 0x0080, 0x0000),  # fault still, bit 7 was set: clear it for the next edge
        (0x000F, 0x000F, 0x0000),  # fault reaction active: wait
    ],
)
def test_the_arming_walk_is_one_transition_per_sync(statusword, last, word):
    assert controlword_toward("OPERATION ENABLED", statusword, last) == word


def test_disarm_is_shutdown():
    assert controlword_toward("READY TO SWITCH ON", 0x0027, 0x000F) == 0x0006
