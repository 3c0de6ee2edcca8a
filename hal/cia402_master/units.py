"""A drive's units, read from its object dictionary: position and velocity increments per
radian of the joint (encoder resolution 0x608F and gear ratio 0x6091), torque in per mille of
the motor's rated torque 0x6076 (0x6071 target, 0x6077 actual, 0x6072 the limit).

The joint is the gear's output shaft: a joint torque is the motor torque times the gear ratio
(motor revolutions per shaft revolution), a joint angle the motor's increments divided by the
increments per shaft radian."""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction

from hal.cia402_od import increments_per_rad
from hal.errors import HalConfigError

INT16_MAX = 32767
"""0x6071 and 0x6077 are INTEGER16: the largest per-mille value they carry."""


@dataclass(frozen=True)
class DriveUnits:
    """The conversions of one drive (all read from it by SDO during boot)."""

    encoder_increments: int
    """0x608F.1: encoder increments per ``motor_revolutions``."""
    motor_revolutions: int
    """0x608F.2."""
    gear_motor_revolutions: int
    """0x6091.1: motor revolutions per ``gear_shaft_revolutions``."""
    gear_shaft_revolutions: int
    """0x6091.2."""
    rated_torque_mnm: int
    """0x6076: the motor's rated torque, mN·m (the base of every per-mille torque)."""

    def __post_init__(self) -> None:
        for name in (
            "encoder_increments",
            "motor_revolutions",
            "gear_motor_revolutions",
            "gear_shaft_revolutions",
            "rated_torque_mnm",
        ):
            if getattr(self, name) <= 0:
                raise HalConfigError(f"drive unit {name} = {getattr(self, name)}: must be > 0")

    @property
    def gear_ratio(self) -> float:
        """Motor revolutions per joint revolution."""
        return self.gear_motor_revolutions / self.gear_shaft_revolutions

    @property
    def increments_per_rad(self) -> float:
        """Encoder increments per radian of the joint."""
        return increments_per_rad(
            self.encoder_increments,
            self.motor_revolutions,
            self.gear_motor_revolutions,
            self.gear_shaft_revolutions,
        )

    @property
    def joint_rated_torque_nm(self) -> float:
        """The rated torque seen at the joint (motor rated torque times the gear ratio), N·m."""
        return self.rated_torque_mnm / 1000.0 * self.gear_ratio

    # --- position and velocity -----------------------------------------------------------
    def position_rad(self, increments: int) -> float:
        """0x6064 (increments) as the joint angle, rad."""
        return increments / self.increments_per_rad

    def velocity_rad_s(self, increments_per_s: int) -> float:
        """0x606C (increments per second) as the joint speed, rad/s."""
        return increments_per_s / self.increments_per_rad

    # --- torque ----------------------------------------------------------------------------
    def torque_nm(self, per_mille: int) -> float:
        """0x6071 / 0x6077 (per mille of rated torque) as the joint torque, N·m."""
        return per_mille / 1000.0 * self.joint_rated_torque_nm

    def per_mille(self, torque_nm: float, limit_per_mille: int = INT16_MAX) -> int:
        """The joint torque ``torque_nm`` as 0x6071, rounded to the nearest per mille and
        clipped to ``+-limit_per_mille`` (0x6072) and to INTEGER16; NaN gives 0."""
        limit = min(int(limit_per_mille), INT16_MAX)
        if math.isnan(torque_nm):
            return 0
        if math.isinf(torque_nm):
            return limit if torque_nm > 0 else -limit
        raw = round(torque_nm / self.joint_rated_torque_nm * 1000.0)
        return max(-limit, min(limit, raw))

    def limit_per_mille(self, torque_nm: float) -> int:
        """The torque limit ``torque_nm`` (N·m at the joint) as 0x6072 (UNSIGNED16, per
        mille), rounded down so the drive never allows more than asked; at most INTEGER16's
        largest value (0x6071 cannot ask for more)."""
        if not (math.isfinite(torque_nm) and torque_nm > 0):
            raise HalConfigError(f"torque limit {torque_nm} N·m: must be finite and > 0")
        return min(INT16_MAX, math.floor(torque_nm / self.joint_rated_torque_nm * 1000.0))


PERIOD_INDICES = (-3, -4, -5, -6, -2, -1, 0)
"""0x60C2.2 exponents tried, in order of preference (milliseconds first)."""


def interpolation_period(period_s: float) -> tuple[int, int]:
    """The control period as 0x60C2 (sub1 value UNSIGNED8, sub2 index INTEGER8; period =
    value x 10^index s), in milliseconds when exact (what drives accept most widely), else
    the finest exact index: 20 ms -> (20, -3), 2.5 ms -> (25, -4), 1 s -> (100, -2). Raises
    when no pair of that form is exact (a rate like 60 Hz)."""
    exact = Fraction(period_s).limit_denominator(10**9)
    for index in PERIOD_INDICES:
        value = exact / Fraction(10) ** index
        if value.denominator == 1 and 1 <= value.numerator <= 255:
            return int(value.numerator), index
    raise HalConfigError(
        f"control period {period_s * 1e3:g} ms cannot be written to 0x60C2 exactly "
        f"(value 1..255 times a power of ten seconds): pick a rate like 50, 100, 200, 250, 500 "
        f"or 1000 Hz"
    )


__all__ = ["INT16_MAX", "DriveUnits", "interpolation_period"]
