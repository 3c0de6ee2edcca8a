"""``hil vision`` on frames (``--source``, or ``camera.model = "image"``): the process body.

The options are the analytic vision process's (``plant_emulator.vision_cli``) plus
``--source``; the ones that shape the analytic camera (``--fps``, ``--noise``, ``--latency``,
``--seed``) belong to the camera, not to the frame grabber, and are refused here; ``--dropout``
(fault injection) pauses the grabber's answers as it pauses the analytic process's (one rule,
:class:`hal.dropout.Dropout`), and is refused with a log, which is re-run offline.
"""

from __future__ import annotations

import argparse
import sys

from hal import strict_json
from hal.arguments import zenoh_session_options
from hal.errors import HalConfigError, HalError, HalStopped
from hal.secoc import bad_mac_clause
from hal.signals import said_stopped_before_start, stop_on_signals

CAMERA_ONLY = ("fps", "noise", "latency", "seed")
FRAMES_ONLY_WITH_LOG = (
    "--frames: only with --source log:RUN.mcap (an offline re-run); a live source publishes "
    "each frame's features on zenoh"
)


def _notice(text: str) -> None:
    print(f"hil vision: warning: {text}", file=sys.stderr, flush=True)


def add_source_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--source",
        metavar="SPEC",
        default=None,
        help="run the image pipeline on frames from SPEC: emulated (the emulated camera over "
        "zenoh), v4l2:/dev/video0, gst:PIPELINE, file:clip.mp4 (or an image sequence, "
        "file:views/view-%%03d.png), or log:run.mcap (offline re-run, nothing published); "
        "default: emulated when camera.model is image, else the analytic camera model",
    )


def run_from_args(args: argparse.Namespace) -> int:
    """Body of ``hil vision --source SPEC``."""
    from hal.config import load_config
    from hal.dropout import Dropout
    from hal.secoc import configure_key
    from vision.process import run_live, run_offline
    from vision.sources import check_source, parse_source

    given = [f"--{name}" for name in CAMERA_ONLY if getattr(args, name, None) is not None]
    dropouts = [Dropout.parse(text) for text in getattr(args, "dropout", None) or []]
    if given:
        raise HalConfigError(
            f"{', '.join(given)}: options of the analytic camera; the image pipeline measures "
            "the frames it gets (set the emulated camera in the [camera] section)"
        )
    kind, _ = parse_source(args.source)
    if getattr(args, "frames", False) and kind != "log":
        raise HalConfigError(FRAMES_ONLY_WITH_LOG)
    if kind == "log" and dropouts:
        raise HalConfigError(
            f"--dropout with --source {args.source}: a log is re-run offline and publishes "
            "nothing, so there is nothing to pause (use a live source)"
        )
    check_source(args.source)  # a missing file or device is told now, not after --wait
    cfg = load_config(args.config)
    if kind != "log":
        cfg = configure_key(cfg, args.key_file, "hil vision")
    if kind == "log":
        lines = []

        def keep(frame, m, msg) -> None:
            lines.append(
                {
                    "seq": frame.seq,
                    "stamp_ns": frame.stamp_ns,
                    "valid": m.valid,
                    "f": list(m.f) if m.f else None,
                    "reason": m.reason,
                }
            )

        stats = run_offline(cfg, args.source, keep, notice=_notice)
        if getattr(args, "frames", False):
            for line in lines:
                print(strict_json.dumps(line))
    else:
        with stop_on_signals() as stop:
            print(
                f"hil vision: image pipeline on {args.source}"
                + "".join(f", dropout {d}" for d in dropouts),
                file=sys.stderr,
                flush=True,
            )
            try:
                stats = run_live(
                    cfg,
                    args.source,
                    stop_event=stop,
                    duration_s=args.duration,
                    dropouts=dropouts,
                    rt_priority=cfg.vision.rt_priority,
                    notice=_notice,
                    **zenoh_session_options(args),
                )
            except HalError as exc:
                if stop.is_set():
                    return said_stopped_before_start(
                        "hil vision", stop, isinstance(exc, HalStopped)
                    )
                raise
    to = sys.stderr if getattr(args, "frames", False) else sys.stdout  # stdout: JSON lines
    if args.json:
        print(strict_json.dumps(stats.as_dict()), file=to, flush=True)
    else:
        rejected = dict(stats.pipeline.get("rejected", {}))
        bad_mac = rejected.pop("bad_mac", 0)
        p99 = stats.detect_us_p99
        why = ", ".join(f"{r} {n}" for r, n in rejected.items() if n)
        if stats.wrong_size_px:  # which sizes: the fix is in [camera], not in the scene
            (w, h), k = stats.wrong_size_px, cfg.camera
            why += f"; frames are {w}x{h}, camera.width_px x height_px {k.width_px}x{k.height_px}"
        print(
            f"hil vision: {stats.frames} frames from {stats.source}, {stats.valid} measured, "
            f"{stats.invalid} without the target{f' ({why})' if why else ''}"
            + bad_mac_clause(bad_mac)
            + (f", detection p99 {p99:.0f} us" if p99 is not None else "")
            + (
                f", {stats.callback_errors} frame(s) lost to errors in zenoh callbacks (a bug)"
                if stats.callback_errors
                else ""
            ),
            file=to,
            flush=True,
        )
    return 0
