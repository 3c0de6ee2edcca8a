"""The sane range of every numeric setting and the check against it."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

from hal.config.values import shown
from hal.errors import HalConfigError

if TYPE_CHECKING:
    from hal.config.rig import RigConfig

_INT_MAX = 2**63 - 1
RANGES: dict[str, tuple[float, float, str]] = {
    # key: (low, high, kind) -- kind "[]" closed, "(]" low open, "[)" high open, "()" open.
    "robot.l1": (0, 10, "(]"),
    "robot.l2": (0, 10, "(]"),
    "robot.lc1": (0, 10, "[]"),
    "robot.lc2": (0, 10, "[]"),
    "robot.m1": (0, 1e4, "(]"),
    "robot.m2": (0, 1e4, "(]"),
    "robot.I1": (0, 1e4, "(]"),
    "robot.I2": (0, 1e4, "(]"),
    "robot.gravity": (0, 100, "[]"),
    "robot.tau_max": (0, 1e4, "(]"),
    "robot.viscous": (0, 1e4, "[]"),
    "robot.coulomb": (0, 1e4, "[]"),
    "camera.s_lambda": (0, 1e6, "(]"),
    "camera.z_wo": (0, 1e3, "(]"),
    "camera.noise_px": (0, 1e4, "[]"),
    "camera.frame_rate_hz": (0, 1e4, "[]"),
    "camera.latency_s": (0, 10, "[]"),
    "camera.seed": (0, _INT_MAX, "[]"),
    "camera.width_px": (16, 8192, "[]"),
    "camera.height_px": (16, 8192, "[]"),
    "camera.principal_point_px": (0, 8192, "[]"),
    "camera.focal_px": (0, 1e6, "[]"),
    "camera.lens_k1": (-10, 10, "[]"),
    "camera.lens_k2": (-100, 100, "[]"),
    "camera.lens_p1": (-1, 1, "[]"),
    "camera.lens_p2": (-1, 1, "[]"),
    "camera.lens_k3": (-1000, 1000, "[]"),
    "camera.exposure_s": (0, 1, "[]"),
    "camera.electrons_per_dn": (0, 1e6, "[]"),
    "camera.read_noise_dn": (0, 255, "[]"),
    "camera.image_log_fps": (0, 1000, "[]"),
    "gains.kp": (0, 1e6, "(]"),
    "gains.alpha": (-1e6, 1e6, "[]"),
    "gains.K": (-1e6, 1e6, "[]"),
    "scenario.q0": (-50, 50, "[]"),
    "scenario.dq0": (-80, 80, "[]"),
    "scenario.f0": (-1e6, 1e6, "[]"),
    "scenario.jump_time": (0, 1e6, "[]"),
    "scenario.f_jump": (-1e6, 1e6, "[]"),
    "rates.control_hz": (1, 2000, "[]"),
    "rates.physics_hz": (1, 100_000, "[]"),
    "rates.state_hz": (1, 100_000, "[]"),
    "rates.status_hz": (1, 1000, "[]"),
    "rhc.horizon": (0, 10, "(]"),
    "rhc.steps": (1, 200, "[]"),
    "rhc.kmax": (1, 50, "[]"),
    "rhc.zeta": (0, 1e4, "(]"),
    "rhc.horizon_growth": (0, 1e4, "[]"),
    "rhc.u_max": (0, 1e4, "(]"),
    "rhc.dummy_weight": (0, 1e6, "(]"),
    "rhc.fd_step": (0, 1e-2, "()"),
    "rhc.residual_bound": (0, 1e12, "(]"),
    "rhc.init_tol": (0, 1, "(]"),
    "rhc.init_iterations": (1, 10_000, "[]"),
    "controller.feature_timeout_s": (0, 10, "(]"),
    "controller.outage_warn_periods": (0, 1e6, "[]"),
    "controller.outage_max_share": (0, 1, "[]"),
    "controller.state_timeout_s": (0, 10, "(]"),
    "controller.spin_us": (0, 100_000, "[]"),
    "controller.rt_priority": (1, 99, "[]"),
    "controller.cpu": (-1, 4095, "[]"),
    "controller.max_clock_skew_s": (0, 1, "[]"),
    "controller.feature_source_takeover_s": (0, 3600, "[]"),
    "dsp.watchdog_periods": (1, 100, "[]"),
    "dsp.encoder_counts": (2, 1 << 24, "[]"),
    "dsp.velocity_filter_hz": (0, 100_000, "[]"),
    "dsp.state_lead_us": (0, 1e6, "[]"),
    "dsp.rt_priority": (0, 99, "[]"),
    "dsp.lockstep_reply_timeout_s": (0, 600, "(]"),
    "dsp.q_min": (-50, 50, "[]"),
    "dsp.q_max": (-50, 50, "[]"),
    "dsp.dq_max": (0, 83, "(]"),
    "cia402.node_id_1": (1, 127, "[]"),
    "cia402.node_id_2": (1, 127, "[]"),
    "cia402.bitrate": (10_000, 1_000_000, "[]"),
    "cia402.rated_torque": (0, 1e4, "(]"),
    "cia402.encoder_increments": (2, 2**31 - 1, "[]"),
    "cia402.sync_loss_periods": (1, 100, "[]"),
    "cia402.lockstep_sync_timeout_s": (0, 600, "(]"),
    "plant.theta1": (0.1, 10, "[]"),
    "plant.theta2": (0.1, 10, "[]"),
    "plant.theta3": (0, 10, "[]"),
    "plant.s_lambda": (0.1, 10, "[]"),
    "plant.z_wo": (0.1, 10, "[]"),
    "vision.fx": (0, 1e6, "(]"),
    "vision.fy": (0, 1e6, "(]"),
    "vision.cx": (-1e5, 1e5, "[]"),
    "vision.cy": (-1e5, 1e5, "[]"),
    "vision.rt_priority": (0, 99, "[]"),
    "vision.k1": (-100, 100, "[]"),
    "vision.k2": (-100, 100, "[]"),
    "vision.p1": (-1, 1, "[]"),
    "vision.p2": (-1, 1, "[]"),
    "vision.k3": (-1000, 1000, "[]"),
}
"""Sane range of every numeric setting (each element of a vector or matrix): a value outside,
like ``rhc.steps = 1000000000`` or ``rates.physics_hz = 1e300``, is a one-line
:class:`HalConfigError` naming the key, before anything allocates or waits."""


def _in_range(value: float, lo: float, hi: float, kind: str) -> bool:
    above = value > lo if kind[0] == "(" else value >= lo
    below = value < hi if kind[1] == ")" else value <= hi
    return above and below


def _flat(value: Any) -> list[float]:
    if isinstance(value, list | tuple):
        return [v for item in value for v in _flat(item)]
    return [value]


def _bound(x: float) -> str:
    """A range's end as written: an integer exactly (``2**63 - 1``), a float as ``:g``."""
    return str(x) if isinstance(x, int) else f"{x:g}"


def _finite(v: Any) -> bool:
    """A number that is not NaN or infinite; any integer is (compared exactly, never as a
    float, which a 400-digit TOML integer overflows)."""
    if isinstance(v, int) and not isinstance(v, bool):
        return True
    return isinstance(v, float) and math.isfinite(v)


def check_ranges(cfg: RigConfig) -> None:
    for key, (lo, hi, kind) in RANGES.items():
        section, _, name = key.partition(".")
        value = getattr(getattr(cfg, section), name)
        for v in _flat(value):
            if not _finite(v):
                raise HalConfigError(f"{key}: must be finite, got {shown(value)}")
            if not _in_range(v, lo, hi, kind):
                interval = f"{kind[0]}{_bound(lo)}, {_bound(hi)}{kind[1]}"
                raise HalConfigError(f"{key}: {shown(value)} is out of range {interval}")
