"""The nominal model's parameters and the controller's gains (eq. 4, 5, 34), from the
configuration. The compiled kernels compute the model's terms (:mod:`~rt_controller.control.
model_kernels`, :mod:`~rt_controller.control.rhc.dynamics`); its plain-NumPy spelling, eq.
(1)-(18) and (25), is their test oracle (``tests/support/nominal_model.py``). This is the
controller's own model; the emulator's physics is a separate implementation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hal.config import RigConfig


@dataclass(frozen=True)
class NominalModel:
    """Parameters of the nominal model and the controller gains (eq. 4, 5, 34)."""

    theta1: float
    theta2: float
    theta3: float
    l1: float
    l2: float
    gain: float
    """s·lambda / z_wo, px/m."""
    kp: float
    alpha: np.ndarray
    R: np.ndarray
    R_inv: np.ndarray
    gravity1: float = 0.0
    """(m1 lc1 + m2 l1) g, N·m: gravity torque amplitude of joint 1 alone."""
    gravity2: float = 0.0
    """m2 lc2 g, N·m."""

    @classmethod
    def from_config(cfg_cls, cfg: RigConfig) -> NominalModel:
        r = cfg.robot
        t1, t2, t3 = r.theta
        alpha = np.array(cfg.gains.alpha, dtype=float)
        R = cfg.gains.R
        return cfg_cls(
            theta1=t1,
            theta2=t2,
            theta3=t3,
            l1=r.l1,
            l2=r.l2,
            gain=cfg.camera.gain,
            kp=cfg.gains.kp,
            alpha=alpha,
            R=R,
            R_inv=np.linalg.inv(R),
            gravity1=(r.m1 * r.lc1 + r.m2 * r.l1) * r.gravity,
            gravity2=r.m2 * r.lc2 * r.gravity,
        )
