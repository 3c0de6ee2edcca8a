"""``hil vision``: the vision process. With ``--source`` (or ``camera.model = "image"``) the
image pipeline of ``vision/`` on frames; otherwise the emulator's analytic camera model
(plant_emulator.vision_cli)."""

from __future__ import annotations

import argparse
from typing import Any


def register(sub: argparse._SubParsersAction) -> None:
    from plant_emulator import vision_cli
    from vision.cli import add_source_option

    p = sub.add_parser(
        "vision",
        help="run the vision process: frames (or the camera model) -> features on zenoh "
        "hil/vision/features",
        description="Measures the image features f of the target and publishes them on zenoh. "
        "On frames (--source, or camera.model = image): OpenCV detection, sub-pixel centre, "
        "undistortion with the calibrated intrinsics ([vision]). Analytic: computes f from the "
        "camera pose the emulator publishes, with noise/frame rate/latency.",
    )
    vision_cli.add_arguments(p)
    add_source_option(p)
    p.add_argument(
        "--frames",
        action="store_true",
        help="with --source log:...: print each frame's measurement as a JSON line (the "
        "summary, --json's too, then goes to stderr)",
    )
    p.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    from hal.arguments import check_zenoh_options
    from hal.config import load_config
    from hal.errors import HalConfigError

    check_zenoh_options(args)
    source = args.source
    if source is None and load_config(args.config).camera.model == "image":
        source = "emulated"
    if source is None:
        from plant_emulator import vision_cli
        from vision.cli import FRAMES_ONLY_WITH_LOG

        if args.frames:  # the analytic camera has no frames to list
            raise HalConfigError(FRAMES_ONLY_WITH_LOG)

        return vision_cli.run_from_args(args)
    from vision.cli import run_from_args

    args.source = source
    return run_from_args(args)


def emulated_camera() -> tuple[Any, Any]:
    """``(render, truth)`` of the emulated camera for ``hil bench vision`` (this module may
    import the emulator; ``rt_controller.rig.bench_vision`` may not): ``render(cfg, q, dq,
    frame)`` the frame taken at joint angles ``q`` moving at ``dq`` (exposure centred on
    ``q``), ``truth(cfg, q)`` the true features of eq. (6) there."""
    import functools

    import numpy as np

    from hal.config import RigConfig, plant_view
    from plant_emulator.camera import camera_pose, project
    from plant_emulator.camera_rig import sensor_from_config
    from plant_emulator.scenario import paper_target

    sensor = functools.lru_cache(maxsize=8)(sensor_from_config)

    def render(cfg: RigConfig, q: np.ndarray, dq: np.ndarray, frame: int) -> np.ndarray:
        robot = plant_view(cfg).robot
        q, dq = np.asarray(q, float), np.asarray(dq, float)
        return sensor(cfg).render(lambda t: camera_pose(robot, q + dq * t), 0.0, frame=frame)

    def truth(cfg: RigConfig, q: np.ndarray) -> tuple[float, float]:
        plant = plant_view(cfg)
        f = project(plant.camera, camera_pose(plant.robot, q), paper_target(plant).position(0.0))
        return (float(f[0]), float(f[1]))

    return render, truth
