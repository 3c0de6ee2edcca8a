"""``hil camera calibrate``: camera matrix and lens distortion from views of a ChArUco board,
written into the rig config's ``[vision]`` section (``vision/calibration.py``).

The views come from the emulated camera (``--source emulated``: the arm at several poses, the
board held at tilts in front of it, :mod:`plant_emulator.calibration_views`), then checked
against the emulated camera's true lens, or from a folder of a real camera's images
(``--images DIR``). One of the ``hil`` subcommands allowed to dispatch to the emulator.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from typing import Any

from hal.arguments import bounded_float, bounded_int, path_given

TARGETS = {"fx_rel": 0.005, "fy_rel": 0.005, "cx_px": 1.0, "cy_px": 1.0, "k1_rel": 0.05}
"""How close a calibration from emulated views must come to the true lens (issue 38)."""
MAX_MARKERS = 100
"""DICT_4X4_100 has 100 markers; a board of X x Y squares needs X*Y // 2 of them."""
EMULATED_VIEWS = 20
EMULATED_ONLY = ("views", "seed", "save_views")
"""Options of the emulated views: refused with --images (they would do nothing)."""
EMULATED_MARKER_MIN = 0.69
"""The emulated board draws a square as 8 cells and a marker needs 6 (4 bits and a border):
a smaller marker/square ratio cannot be drawn."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "camera",
        help="camera tools: calibrate the camera the vision pipeline sees through",
        description="Camera tools. `hil camera calibrate` finds the camera matrix and lens "
        "distortion from views of a ChArUco board and writes them into the rig config.",
    )
    tools = p.add_subparsers(dest="camera_command", metavar="TOOL", required=True)
    c = tools.add_parser(
        "calibrate",
        help="camera matrix and distortion from ChArUco views -> [vision] of the rig config",
        description="Detects the ChArUco board (14x10 squares of 30 mm, markers 22.5 mm, "
        "DICT_4X4_100; --squares/--square-mm/--marker-mm for another) in every view, refines "
        "its corners to sub-pixel and fits the camera matrix and (k1, k2, p1, p2, k3) with "
        "cv2.calibrateCamera (k3 and p1, p2 held at 0 unless --k3 / --tangential). The result "
        "goes into the [vision] keys of the --config file (or --write FILE; with neither it is "
        "only printed), the rest of the file untouched, and sets vision.calibrated = true. "
        "With --source emulated it is also compared with the emulated camera's true lens "
        "([camera]); exit 1 if fx, fy are off by more than 0.5 %, cx, cy by more than 1 px or "
        "k1 by more than 5 %.",
    )
    c.add_argument("--config", metavar="FILE", help="rig config (TOML): the camera to calibrate")
    src = c.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--source",
        choices=("emulated",),
        help="views from the emulated camera, the arm at several poses",
    )
    src.add_argument("--images", metavar="DIR", help="views: the image files of a folder")
    c.add_argument(
        "--views",
        type=bounded_int(3, 500, what="views"),
        default=None,
        metavar="N",
        help=f"emulated views ({EMULATED_VIEWS})",
    )
    c.add_argument(
        "--seed",
        type=bounded_int(0, 2**32 - 1, what="seed"),
        default=None,
        help="emulated views: poses and noise (0)",
    )
    c.add_argument(
        "--write", type=path_given, metavar="FILE", help="write the result here instead of --config"
    )
    c.add_argument("--save-views", metavar="DIR", help="emulated views: also save them as PNG")
    c.add_argument(
        "--squares",
        type=bounded_int(3, 2 * MAX_MARKERS // 3 + 1, what="squares"),
        nargs=2,
        metavar=("X", "Y"),
        default=(14, 10),
        help="board squares across and down (14 10)",
    )
    c.add_argument(
        "--square-mm",
        type=bounded_float(1, 1000, lo_inclusive=True, what="square side in mm"),
        default=30.0,
        help="square side, mm (30)",
    )
    c.add_argument(
        "--marker-mm",
        type=bounded_float(0, 1000, what="marker side in mm"),
        default=22.5,
        help="marker side, mm (22.5)",
    )
    c.add_argument("--k3", action="store_true", help="also fit k3 (default: held at 0)")
    c.add_argument("--tangential", action="store_true", help="also fit p1, p2 (default: held at 0)")
    c.add_argument("--json", action="store_true", help="print one JSON object")
    c.set_defaults(handler=run_calibrate)


def _spec(args: argparse.Namespace) -> Any:
    from hal.errors import HalConfigError
    from vision.calibration import CharucoSpec

    sx, sy = args.squares  # each at least 3 (its argparse type)
    if sx * sy // 2 > MAX_MARKERS:
        raise HalConfigError(
            f"--squares {sx} {sy}: a DICT_4X4_100 board has at most {MAX_MARKERS} markers "
            f"(X * Y up to {2 * MAX_MARKERS + 1} squares), this one needs {sx * sy // 2}"
        )
    if not (0 < args.marker_mm < args.square_mm):
        raise HalConfigError(
            f"--marker-mm must be positive and below --square-mm ({args.square_mm:g}), "
            f"got {args.marker_mm:g}"
        )
    if not args.images and args.marker_mm < EMULATED_MARKER_MIN * args.square_mm:
        raise HalConfigError(
            f"--marker-mm {args.marker_mm:g}: the emulated board needs markers of at least "
            f"{EMULATED_MARKER_MIN:g} of --square-mm ({args.square_mm:g})"
        )
    return CharucoSpec(sx, sy, args.square_mm / 1000.0, args.marker_mm / 1000.0)


def truth_errors(calibration: Any, cfg: Any) -> dict[str, float]:
    """The calibration against the emulated camera's true lens: fx, fy, k1 relative, cx, cy
    in px."""
    from hal.config import plant_view

    c = plant_view(cfg).camera
    fx, fy = c.true_focal_px
    cx, cy = c.true_principal_point_px
    return {
        "fx_rel": calibration.fx / fx - 1.0,
        "fy_rel": calibration.fy / fy - 1.0,
        "cx_px": calibration.cx - cx,
        "cy_px": calibration.cy - cy,
        "k1_rel": float(calibration.distortion[0]) / c.lens_k1 - 1.0 if c.lens_k1 else math.nan,
    }


def run_calibrate(args: argparse.Namespace) -> int:
    from hal.config import load_config
    from hal.errors import HalConfigError
    from rt_controller.commands.output import output_file
    from vision.calibration import calibrate, check_writable, read_images, write_vision_section

    given = [name for name in EMULATED_ONLY if getattr(args, name) is not None]
    if args.images and given:
        raise HalConfigError(
            f"--{given[0].replace('_', '-')}: only with --source emulated (--images calibrates "
            "from the folder's views as they are)"
        )
    if args.config and not os.path.lexists(args.config):  # calibrate the camera of a rig
        raise HalConfigError(
            f"--config {args.config}: no such file (start from a copy of examples/rig.toml, "
            "set [camera] to your camera, then calibrate)"
        )
    cfg = load_config(args.config)
    spec = _spec(args)
    if args.write:  # a bad path is refused before the views are taken
        output_file(args.write, "--write")
    if args.write or args.config:  # so is a read-only config
        check_writable(args.write or args.config)
    if args.save_views:  # views of two runs in one folder would be calibrated together
        from pathlib import Path

        earlier = sorted(Path(args.save_views).glob("view-*.png"))
        if earlier:
            raise HalConfigError(
                f"--save-views {args.save_views}: already holds {len(earlier)} saved views "
                "(view-*.png): give an empty or new folder"
            )
    if args.images:
        views = read_images(args.images)
    else:
        from plant_emulator.calibration_views import board_views

        n = EMULATED_VIEWS if args.views is None else args.views
        views = board_views(cfg, spec.cells(), spec.cell_m, n, seed=args.seed or 0)
        if args.save_views:
            _save(views, args.save_views)
    cal = calibrate(views, spec, k3=args.k3, tangential=args.tangential)
    summary: dict[str, Any] = {"source": args.images or "emulated", **cal.as_dict()}
    status = 0
    if not args.images:
        errors = truth_errors(cal, cfg)
        misses = [k for k, lim in TARGETS.items() if not abs(errors[k]) <= lim]
        summary["truth"] = errors
        summary["within_targets"] = not misses
        if misses:
            print(
                "hil camera calibrate: off the emulated lens by more than the targets: "
                + ", ".join(f"{k} {errors[k]:+.4g} (limit {TARGETS[k]:g})" for k in misses),
                file=sys.stderr,
            )
            status = 1
    c = cfg.camera
    if (cal.width, cal.height) != (c.width_px, c.height_px):
        print(
            f"hil camera calibrate: warning: the views are {cal.width}x{cal.height} but "
            f"camera.width_px x height_px is {c.width_px}x{c.height_px}: set them to the "
            "camera's, the vision pipeline rejects frames of another size (wrong_size)",
            file=sys.stderr,
        )
    target = args.write or args.config
    try:
        if target:
            write_vision_section(target, cal)
    except (HalConfigError, OSError):
        summary["written"] = None  # the calibration is printed before the error: not lost
        _print(summary, args.json)
        raise
    summary["written"] = target
    _print(summary, args.json)
    if not target and not args.json:
        print("note: not written anywhere; give --config FILE (or --write FILE)")
    return status


def _print(summary: dict[str, Any], as_json: bool) -> None:
    from rt_controller.commands.output import print_summary

    if as_json:
        print_summary(summary, True, "hil camera calibrate")
    else:
        flat = {k: v for k, v in summary.items() if k != "truth"}
        flat.update({f"truth.{k}": v for k, v in summary.get("truth", {}).items()})
        print_summary(flat, False, "hil camera calibrate")


def _save(views: list[Any], folder: str) -> None:
    import cv2

    from rt_controller.commands.output import output_dir

    root = output_dir(folder, "--save-views")
    for i, img in enumerate(views):
        cv2.imwrite(str(root / f"view-{i:03d}.png"), img)
