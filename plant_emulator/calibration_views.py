"""Views of a calibration board through the emulated camera, as an operator would take them.

The arm moves the camera to a different pose for every view, and the board is held in front of
it at a tilt (20-40 degrees about a random in-plane axis, turned at random about its normal,
shifted so that its corners sweep the image's edges): the tilts are what lets calibration
separate the focal length from the distance. Views are deterministic for a seed.
"""

from __future__ import annotations

import math

import numpy as np

from hal.config import RigConfig
from plant_emulator.camera import camera_pose
from plant_emulator.camera_rig import sensor_from_config
from plant_emulator.camera_sensor import Placement
from plant_emulator.camera_textures import GridTexture

PAPER = 0.8
"""Reflectance around the board (and of its white cells' surroundings)."""


_TOWARD = ((1, 1), (-1, -1), (1, -1), (-1, 1), (1, 0), (-1, 0), (0, 1), (0, -1), (0, 0))
"""Where the board's centre goes in the image, view after view (fractions of the half-size)."""


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' rotation matrix about the unit ``axis``."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def board_views(
    cfg: RigConfig, cells: np.ndarray, cell_m: float, n_views: int, seed: int = 0
) -> list[np.ndarray]:
    """``n_views`` grey frames of the board ``cells`` (reflectances, one per cell of side
    ``cell_m``) seen by the emulated camera of ``cfg`` (its true lens and noise)."""
    rng = np.random.default_rng(seed)
    sensor = sensor_from_config(cfg)
    texture = GridTexture(np.asarray(cells, dtype=float), (0.0, 0.0), cell_m, PAPER)
    rows, cols = texture.cells.shape
    width, height = cols * cell_m, rows * cell_m
    z = sensor.z_wo
    k = sensor.intrinsics
    half_w = (sensor.resolution.width / 2) / k.fx * z
    half_h = (sensor.resolution.height / 2) / k.fy * z
    q0 = np.array(cfg.scenario.q0)
    views = []
    for i in range(n_views):
        pose = camera_pose(cfg.robot, q0 + rng.uniform(-0.3, 0.3, 2))
        c, s = math.cos(pose.phi), math.sin(pose.phi)
        tilt_axis = np.array([*np.array([math.cos(a := rng.uniform(0, math.pi)), math.sin(a)]), 0])
        spin = _rotation(np.array([0.0, 0.0, 1.0]), rng.uniform(-math.pi, math.pi))
        rot = _rotation(tilt_axis, rng.uniform(math.radians(25), math.radians(45))) @ spin
        # the board's centre: pushed towards the image's corners and edges in turn, where the
        # lens distorts most (and once through the middle)
        toward = _TOWARD[i % len(_TOWARD)]
        offset = (np.array(toward) * 0.55 + rng.uniform(-0.1, 0.1, 2)) * (half_w, half_h)
        depth = z * rng.uniform(0.7, 1.0)
        centre_cam = np.array([offset[0], offset[1], depth])
        to_world = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        centre = np.array([pose.x, pose.y, 0.0]) + to_world @ centre_cam
        au, av = to_world @ rot[:, 0], to_world @ rot[:, 1]
        origin = centre - au * width / 2 - av * height / 2
        views.append(sensor.render_view(pose, Placement(origin, au, av), texture, frame=i))
    return views
