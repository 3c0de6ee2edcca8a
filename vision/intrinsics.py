"""The detector's camera model: the calibrated intrinsics and OpenCV's distortion model, and the
conversion of a detected pixel to the paper's features f.

The paper's f (eq. 6) is the target's position in the ideal (distortion-free) image, in px about
the principal point: ``f = (u_ideal - cx, v_ideal - cy)``, with the image's u axis along the
camera's x axis (the hand's heading q1 + q2) and v along its y axis. A detected (distorted) pixel
is undistorted with the calibrated camera matrix and distortion coefficients (iteratively, to
1e-12 of a normalised unit) and scaled back by the focal lengths.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from hal.config import RigConfig

UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
"""Iterations of OpenCV's point undistortion: its default (5 iterations) leaves up to 0.1 px
near the corners of a strongly distorted lens."""


@dataclass(frozen=True)
class Intrinsics:
    """Image size (px), focal lengths and principal point (px), OpenCV distortion
    coefficients ``(k1, k2, p1, p2, k3)``."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def distortion(self) -> np.ndarray:
        return np.array(self.dist, dtype=np.float64)

    @property
    def distorted(self) -> bool:
        return any(self.dist)

    def features(self, uv: tuple[float, float]) -> tuple[float, float]:
        """The paper's f (px about the principal point, ideal image) of a detected pixel."""
        if not self.distorted:
            return (float(uv[0]) - self.cx, float(uv[1]) - self.cy)
        pts = np.array([[uv]], dtype=np.float64)
        xn = cv2.undistortPoints(
            pts, self.matrix, self.distortion, criteria=UNDISTORT_CRITERIA
        ).reshape(2)
        return (float(xn[0]) * self.fx, float(xn[1]) * self.fy)

    def pixel(self, f: tuple[float, float]) -> tuple[float, float]:
        """Inverse of :meth:`features`: where the lens puts a point of features ``f``."""
        obj = np.array([[[f[0] / self.fx, f[1] / self.fy, 1.0]]], dtype=np.float64)
        uv, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), self.matrix, self.distortion)
        return (float(uv[0, 0, 0]), float(uv[0, 0, 1]))


def intrinsics_from_config(cfg: RigConfig) -> Intrinsics:
    """The detector's intrinsics: ``[vision]`` when ``vision.calibrated`` (what ``hil camera
    calibrate`` wrote), else the camera's nominal values (the emulated lens)."""
    return Intrinsics(**_nominal(cfg)) if not cfg.vision.calibrated else _calibrated(cfg)


def _nominal(cfg: RigConfig) -> dict[str, object]:
    """The emulated camera's true intrinsics (``[camera]``, nominal: not the plant's factors)."""
    cam = cfg.camera
    fx, fy = cam.true_focal_px
    cx, cy = cam.true_principal_point_px
    return {
        "width": int(cam.width_px),
        "height": int(cam.height_px),
        "fx": float(fx),
        "fy": float(fy),
        "cx": float(cx),
        "cy": float(cy),
        "dist": tuple(float(d) for d in cam.true_lens),
    }


def _calibrated(cfg: RigConfig) -> Intrinsics:
    v = cfg.vision
    nominal = _nominal(cfg)
    return Intrinsics(
        width=nominal["width"],  # type: ignore[arg-type]
        height=nominal["height"],  # type: ignore[arg-type]
        fx=v.fx,
        fy=v.fy,
        cx=v.cx,
        cy=v.cy,
        dist=(v.k1, v.k2, v.p1, v.p2, v.k3),
    )
