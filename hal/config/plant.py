"""The plant as it physically is: ``[robot]`` (the arm), ``[camera]`` (the camera on the hand)
and ``[plant]`` (how the emulated plant differs from the controller's nominal model), and
:func:`plant_view`, the numbers the emulator is built from."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING

from hal.config.values import Vec2

if TYPE_CHECKING:
    from hal.config.rig import RigConfig


@dataclass(frozen=True)
class RobotConfig:
    """Two-link planar arm (eq. 1-5). Lengths in m, masses in kg, inertias in kg·m²."""

    l1: float = 0.26
    l2: float = 0.26
    lc1: float = 0.0983
    lc2: float = 0.0229
    m1: float = 6.5225
    m2: float = 2.0458
    I1: float = 0.1213
    I2: float = 0.0116
    gravity: float = 0.0
    """Gravity along -Y_w in m/s²; 0 for the horizontal plane of the paper's rig."""
    tau_max: Vec2 = (150.0, 15.0)
    """Amplifier torque limits per joint, N·m."""
    viscous: Vec2 = (0.0, 0.0)
    """Viscous joint friction, N·m·s/rad (emulator only)."""
    coulomb: Vec2 = (0.0, 0.0)
    """Coulomb joint friction, N·m (emulator only)."""

    @property
    def theta(self) -> tuple[float, float, float]:
        """Base parameters theta1..theta3 of eq. (4)-(5)."""
        t1 = self.m1 * self.lc1**2 + self.m2 * self.l1**2 + self.I1
        t2 = self.m2 * self.lc2**2 + self.I2
        t3 = self.m2 * self.l1 * self.lc2
        return (t1, t2, t3)


@dataclass(frozen=True)
class CameraConfig:
    """Ideal pinhole camera on the hand (eq. 6): f = (s·lambda / z_wo) R_wc^T (p_wo - p_wc)."""

    s_lambda: float = 1230.0
    """Scale factor times focal length, px."""
    z_wo: float = 0.9
    """Depth of the target plane, m."""
    noise_px: float = 0.0
    """The analytic camera's Gaussian pixel noise on each feature (std); 0 = off. A rig on the
    rendering camera refuses it: there the noise is the sensor's (``read_noise_dn``,
    ``electrons_per_dn``)."""
    frame_rate_hz: float = 0.0
    """Camera frame rate; 0 = the default: 60 fps (the XC-HR57's) for ``hil vision`` and the
    emulated camera in realtime and the analytic vision process in lockstep, a fresh image
    whenever the controller asks in ``hil simulate``. The emulated camera in lockstep gives
    exactly one frame per control period whatever this is."""
    latency_s: float = 0.0
    """Delay between capture and delivery of a feature vector; 0 = off."""
    seed: int = 0
    """Seed of the pixel-noise generator (repetitions of an experiment differ by it)."""
    model: str = "image"
    """image: the emulated camera renders frames and the vision process measures f from the
    pixels (``hil up``, ``hil experiment``); analytic: f from eq. (6) plus ``noise_px`` (fast
    sweeps, ``hil simulate``)."""
    width_px: int = 640
    """Image width of the emulated camera, px."""
    height_px: int = 480
    """Image height of the emulated camera, px."""
    principal_point_px: Vec2 = (0.0, 0.0)
    """True principal point (cx, cy), px; (0, 0): the image centre ((w - 1) / 2, (h - 1) / 2)."""
    focal_px: Vec2 = (0.0, 0.0)
    """True focal lengths (fx, fy), px; (0, 0): s·lambda on both axes (square pixels, eq. 6)."""
    lens_k1: float = -0.1
    """True lens of the emulated camera, OpenCV's model: radial k1."""
    lens_k2: float = 0.05
    """True lens: radial k2."""
    lens_p1: float = 0.0
    """True lens: tangential p1."""
    lens_p2: float = 0.0
    """True lens: tangential p2."""
    lens_k3: float = 0.0
    """True lens: radial k3."""
    exposure_s: float = 0.004
    """Exposure time; the frame is stamped at its middle and blurred by the motion during it
    (0: an instant, no blur)."""
    electrons_per_dn: float = 40.0
    """Shot noise: photo-electrons per grey level (variance DN / this); 0 = off."""
    read_noise_dn: float = 0.5
    """Read noise, standard deviation in grey levels; 0 = off."""
    image_log_fps: float = 10.0
    """Rate of the decimated image stream in the log and on ``hil monitor``; 0 = none."""

    @property
    def gain(self) -> float:
        """s·lambda / z_wo in px/m (1367 for the paper's camera)."""
        return self.s_lambda / self.z_wo

    @property
    def true_focal_px(self) -> tuple[float, float]:
        """The emulated camera's (fx, fy), px (``focal_px``, or s·lambda)."""
        fx, fy = self.focal_px
        return (fx, fy) if (fx, fy) != (0.0, 0.0) else (self.s_lambda, self.s_lambda)

    @property
    def true_principal_point_px(self) -> tuple[float, float]:
        """The emulated camera's (cx, cy), px (``principal_point_px``, or the image centre)."""
        cx, cy = self.principal_point_px
        if (cx, cy) != (0.0, 0.0):
            return (cx, cy)
        return ((self.width_px - 1) / 2, (self.height_px - 1) / 2)

    @property
    def true_lens(self) -> tuple[float, float, float, float, float]:
        """The emulated camera's distortion coefficients in OpenCV's order."""
        return (self.lens_k1, self.lens_k2, self.lens_p1, self.lens_p2, self.lens_k3)


@dataclass(frozen=True)
class PlantConfig:
    """Model mismatch: how the emulated plant differs from the controller's nominal model.

    Factors on the nominal numbers of ``[robot]`` and ``[camera]`` (1 = the plant is the
    nominal model, the default). Only the emulator's physics, camera and vision apply them
    (:func:`plant_view`); the controller always works with the nominal sections, so a
    ``[plant]`` other than 1 is a plant the controller does not know exactly. Each run's config
    (its log's metadata, a sweep's row) carries the section.
    """

    theta1: float = 1.0
    """Factor on theta1 = m1 lc1² + m2 l1² + I1 (eq. 4), realised through the plant's I1."""
    theta2: float = 1.0
    """Factor on theta2 = m2 lc2² + I2, realised through the plant's I2."""
    theta3: float = 1.0
    """Factor on theta3 = m2 l1 lc2, realised through the plant's lc2 (I2 keeps theta2)."""
    s_lambda: float = 1.0
    """Factor on camera.s_lambda (scale factor times focal length)."""
    z_wo: float = 1.0
    """Factor on camera.z_wo (depth of the target plane)."""

    @property
    def nominal(self) -> bool:
        return all(getattr(self, f.name) == 1.0 for f in dataclasses.fields(self))


def plant_robot(cfg: RigConfig) -> RobotConfig:
    """The plant's robot: the nominal one with theta1..theta3 scaled by ``[plant]``."""
    r, p = cfg.robot, cfg.plant
    if p.theta1 == p.theta2 == p.theta3 == 1.0:
        return r
    t1, t2, _ = r.theta
    lc2 = r.lc2 * p.theta3
    I2 = p.theta2 * t2 - r.m2 * lc2**2
    I1 = p.theta1 * t1 - r.m1 * r.lc1**2 - r.m2 * r.l1**2
    return dataclasses.replace(r, lc2=lc2, I1=I1, I2=I2)


def plant_view(cfg: RigConfig) -> RigConfig:
    """What the emulated plant is: ``cfg`` with ``[robot]`` and ``[camera]`` replaced by the
    plant's numbers (the nominal ones times the ``[plant]`` factors) and ``[plant]`` back to 1.
    The emulator's physics, camera and vision are built from this; the controller never is."""
    p = cfg.plant
    if p.nominal:
        return cfg
    camera = dataclasses.replace(
        cfg.camera, s_lambda=cfg.camera.s_lambda * p.s_lambda, z_wo=cfg.camera.z_wo * p.z_wo
    )
    return dataclasses.replace(cfg, robot=plant_robot(cfg), camera=camera, plant=PlantConfig())
