"""The emulated camera's optics: pinhole intrinsics and OpenCV's lens distortion model (the
"true" lens the calibration is checked against), forward and inverse."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_UNDISTORT_TOL = 1e-13
_UNDISTORT_MAX_ITER = 200


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in px (OpenCV's camera matrix)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class LensDistortion:
    """OpenCV's distortion model, coefficients in OpenCV's order (k1, k2, p1, p2, k3)."""

    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    def coefficients(self) -> np.ndarray:
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    @property
    def none(self) -> bool:
        return not np.any(self.coefficients())


def distort(xn: np.ndarray, yn: np.ndarray, d: LensDistortion) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's forward lens model: ideal normalised coordinates -> distorted ones."""
    r2 = xn * xn + yn * yn
    radial = 1.0 + r2 * (d.k1 + r2 * (d.k2 + r2 * d.k3))
    xy = xn * yn
    xd = xn * radial + 2.0 * d.p1 * xy + d.p2 * (r2 + 2.0 * xn * xn)
    yd = yn * radial + d.p1 * (r2 + 2.0 * yn * yn) + 2.0 * d.p2 * xy
    return xd, yd


def undistort(
    xd: np.ndarray, yd: np.ndarray, d: LensDistortion
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Invert :func:`distort` by fixed-point iteration to ~1e-13: ``(xn, yn, converged)``; a
    point the lens cannot reach (a strong lens far off axis) is NaN and not converged."""
    xd = np.asarray(xd, dtype=float)
    yd = np.asarray(yd, dtype=float)
    if d.none:
        return xd.copy(), yd.copy(), np.ones(xd.shape, dtype=bool)
    xn, yn = xd.copy(), yd.copy()
    for _ in range(_UNDISTORT_MAX_ITER):
        r2 = xn * xn + yn * yn
        radial = 1.0 + r2 * (d.k1 + r2 * (d.k2 + r2 * d.k3))
        xy = xn * yn
        dx = 2.0 * d.p1 * xy + d.p2 * (r2 + 2.0 * xn * xn)
        dy = d.p1 * (r2 + 2.0 * yn * yn) + 2.0 * d.p2 * xy
        with np.errstate(divide="ignore", invalid="ignore"):
            xn, yn = (xd - dx) / radial, (yd - dy) / radial
        fx, fy = distort(xn, yn, d)
        err = np.hypot(fx - xd, fy - yd)
        if np.all(err[np.isfinite(err)] < _UNDISTORT_TOL) and np.all(np.isfinite(err)):
            break
    fx, fy = distort(xn, yn, d)
    ok = np.isfinite(xn) & np.isfinite(yn) & (np.hypot(fx - xd, fy - yd) < 1e-9)
    return np.where(ok, xn, np.nan), np.where(ok, yn, np.nan), ok
