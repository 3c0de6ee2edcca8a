"""``hil vision`` on the command line: its options and the process body around
:func:`plant_emulator.vision_node.run_vision`.

Building the parser imports nothing heavy (no numpy, zenoh or numba), so ``hil --help`` stays fast;
the vision node is imported when the command runs.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from hal import strict_json
from hal.arguments import add_key_option, bounded_float, duration, zenoh_session_options
from hal.errors import HalError, HalStopped
from hal.signals import run_standalone, said_stopped_before_start, stop_on_signals

if TYPE_CHECKING:
    from hal.config import RigConfig


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hil vision`` (for the lead's subcommand wiring)."""
    p.add_argument("--config", metavar="FILE", help="rig config TOML (default: embedded)")
    add_key_option(p)
    p.add_argument(
        "--fps",
        type=bounded_float(0.0, 10_000.0, lo_inclusive=True, what="frame rate in Hz"),
        default=None,
        metavar="HZ",
        help="frame rate; 0 = one frame per pose (default: camera.frame_rate_hz, else 60)",
    )
    p.add_argument(
        "--noise",
        type=bounded_float(0.0, 1000.0, lo_inclusive=True, what="pixel noise"),
        metavar="PX",
        help="pixel noise std (camera.noise_px)",
    )
    p.add_argument(
        "--latency",
        type=bounded_float(0.0, 10.0, lo_inclusive=True, what="latency in seconds"),
        metavar="S",
        help="delivery delay (camera.latency_s)",
    )
    p.add_argument(
        "--seed",
        type=int,
        help="noise seed (camera.seed); a run after a scenario reset that names a seed uses that",
    )
    p.add_argument(
        "--clock",
        choices=("auto", "lockstep", "realtime"),
        default="auto",
        help="auto follows each pose's lockstep flag (default)",
    )
    p.add_argument(
        "--zenoh-endpoint",
        metavar="EP",
        help="loopback endpoint tcp/127.0.0.1:PORT (default: transport.zenoh_endpoint)",
    )
    p.add_argument(
        "--zenoh-config",
        metavar="FILE",
        help="zenoh json5 config replacing the loopback defaults (multi-host setups)",
    )
    p.add_argument(
        "--zenoh-role",
        choices=("auto", "hub", "client"),
        default=None,
        help="client = connect to the emulator's hub (default), hub = listen on the endpoint "
        "(run without an emulator), auto = hub if the port is free; not with --zenoh-config, "
        "whose mode and listen endpoints set the role",
    )
    p.add_argument(
        "--wait",
        type=bounded_float(0.0, 3600.0, lo_inclusive=True, what="wait in seconds"),
        default=None,
        metavar="S",
        help="wait for the hub (default 10 s); not with --zenoh-config, whose connect "
        "timeout_ms sets it",
    )
    p.add_argument(
        "--duration",
        type=duration(zero_means_forever=True),
        default=0.0,
        metavar="S",
        help="0 = until SIGTERM",
    )
    p.add_argument(
        "--dropout",
        action="append",
        default=[],
        metavar="START:DURATION",
        help="fault injection: pause publishing for DURATION s from START s of simulation time "
        "(lockstep answers each pose with valid=0 meanwhile); repeatable",
    )
    p.add_argument("--json", action="store_true", help="print the final counters as one JSON line")


def _config(args: argparse.Namespace) -> RigConfig:
    from hal.config import load_config

    cfg = load_config(args.config)
    overrides: dict[str, Any] = {}
    for opt, key in (("noise", "noise_px"), ("latency", "latency_s"), ("seed", "seed")):
        value = getattr(args, opt)
        if value is not None:
            overrides[f"camera.{key}"] = value
    from hal.secoc import configure_key

    cfg = cfg.with_overrides(overrides) if overrides else cfg
    return configure_key(cfg, args.key_file, "hil vision")


def run_from_args(args: argparse.Namespace) -> int:
    """Body of ``hil vision``: SIGTERM/SIGINT end it cleanly with status 0."""
    from plant_emulator.vision_node import run_vision
    from plant_emulator.vision_timing import Dropout, resolve_fps

    cfg = _config(args)
    fps = resolve_fps(cfg, args.fps)
    dropouts = [Dropout.parse(text) for text in getattr(args, "dropout", None) or []]
    lockstep = {"auto": None, "lockstep": True, "realtime": False}[args.clock]
    with stop_on_signals() as stop:
        print(
            f"hil vision: {fps:g} fps, clock {args.clock}, "
            f"zenoh {args.zenoh_config or args.zenoh_endpoint or cfg.transport.zenoh_endpoint}"
            + "".join(f", dropout {d}" for d in dropouts),
            file=sys.stderr,
            flush=True,
        )
        try:
            stats = run_vision(
                cfg,
                fps=fps,
                lockstep=lockstep,
                stop_event=stop,
                duration_s=args.duration,
                dropouts=dropouts,
                **zenoh_session_options(args),
            )
        except HalError as exc:
            if stop.is_set():  # told to stop while waiting for the hub
                return said_stopped_before_start("hil vision", stop, isinstance(exc, HalStopped))
            raise
    if args.json:
        print(strict_json.dumps(stats.as_dict()), flush=True)
    else:
        from hal.secoc import bad_mac_clause

        bad_mac = stats.pose_rx.get("bad_mac", 0)
        print(
            f"hil vision: {stats.poses} poses, {stats.frames} frames, "
            f"{stats.published} messages published, "
            f"{stats.pose_rx.get('rejected', 0) - bad_mac} poses rejected"
            + bad_mac_clause(bad_mac),
            flush=True,
        )
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``hil vision``."""
    parser = argparse.ArgumentParser(
        prog="hil vision",
        description="Vision process: camera poses from the emulator in, image features out "
        "(zenoh key hil/vision/features).",
    )
    add_arguments(parser)
    args = parser.parse_args(argv)
    return run_standalone("hil vision", lambda: run_from_args(args))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
