"""The rig's emulated camera from its configuration: the paper's scene (the target marker where
the scenario puts it) and the sensor (the "true" lens, noise and exposure of ``[camera]``)."""

from __future__ import annotations

from hal.config import RigConfig, plant_view
from plant_emulator.camera_lens import Intrinsics, LensDistortion
from plant_emulator.camera_sensor import CameraSensor, Resolution, Scene, SensorNoise
from plant_emulator.camera_textures import marker_texture
from plant_emulator.scenario import paper_target


def target_scene(cfg: RigConfig) -> Scene:
    """The paper's scene: the rig's target marker where the scenario puts it (the jump included)."""
    target = paper_target(plant_view(cfg))
    return lambda t: marker_texture(target.position(t))


def sensor_from_config(
    cfg: RigConfig, scene: Scene | None = None, seed: int | None = None
) -> CameraSensor:
    """The emulated camera of ``cfg`` (the plant's: :func:`hal.config.plant_view`), looking at
    ``scene`` (default: :func:`target_scene`)."""
    c = plant_view(cfg).camera
    fx, fy = c.true_focal_px
    cx, cy = c.true_principal_point_px
    return CameraSensor(
        Intrinsics(fx, fy, cx, cy),
        LensDistortion(*c.true_lens),
        Resolution(c.width_px, c.height_px),
        SensorNoise(c.electrons_per_dn, c.read_noise_dn),
        c.exposure_s,
        c.seed if seed is None else seed,
        z_wo=c.z_wo,
        scene=target_scene(cfg) if scene is None else scene,
    )
