"""``hil up``: emulator, vision and controller as separate processes, one summary."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hal.arguments import duration
from hal.config import LAW_NAMES


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "up",
        help="start emulator, vision and controller, run the paper scenario, stop, summarise",
        description="Starts `hil emulator`, `hil vision` and `hil controller` as separate "
        "processes on the embedded defaults, waits --duration, stops them cleanly and prints "
        "final |f|, J, deadline misses, solve time and the log path.",
    )
    p.add_argument("--law", choices=LAW_NAMES, help="control law (default: config)")
    p.add_argument("--duration", type=duration(), default=10.0, metavar="S", help="default 10")
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="DSP clocks the run with Sync frames: deterministic, faster than real time",
    )
    p.add_argument(
        "--wall-timeout",
        type=duration(),
        metavar="S",
        help="wall-clock seconds before the run is called hung (default: duration + 60 s; "
        "lockstep: 20 x duration + 60 s)",
    )
    p.add_argument("--can", metavar="INTERFACE[:CHANNEL]", help="CAN bus (default: auto)")
    p.add_argument("--config", metavar="FILE", help="rig configuration (TOML)")
    p.add_argument("--log", metavar="FILE.mcap", help="controller log path")
    p.add_argument(
        "--key-file",
        metavar="FILE",
        help="rig key for all three processes (default: a fresh key for this run, so two rigs "
        "never share one; give one when a process of the rig runs elsewhere)",
    )
    p.add_argument("--zenoh-endpoint", metavar="tcp/127.0.0.1:PORT", help="default: a free port")
    p.add_argument(
        "--monitor",
        action="store_true",
        help="also start `hil monitor`: a Foxglove WebSocket live view (ws://127.0.0.1:8765)",
    )
    p.add_argument("--monitor-port", type=int, metavar="PORT", help="live view port (8765)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from rt_controller.commands.output import print_summary
    from rt_controller.rig.processes import RigOptions, run_rig
    from rt_controller.rig.supervise import RigInterrupted, supervised

    try:
        with supervised():
            summary = run_rig(
                RigOptions(
                    config=args.config,
                    law=args.law,
                    duration_s=args.duration,
                    lockstep=args.lockstep,
                    wall_timeout_s=args.wall_timeout,
                    can=args.can,
                    zenoh_endpoint=args.zenoh_endpoint,
                    log=Path(args.log) if args.log else None,
                    monitor=args.monitor or args.monitor_port is not None,
                    monitor_port=args.monitor_port,
                    key_file=Path(args.key_file) if args.key_file else None,
                )
            )
    except RigInterrupted as exc:
        print(
            f"hil up: {exc}: stopped the rig (controller first), nothing left running",
            file=sys.stderr,
        )
        return exc.exit_code
    keys = (
        "law", "ticks", "J", "f_final", "f_final_norm", "deadline_misses", "missed_periods",
        "stale_features", "stale_states", "late_states", "old_states", "fallbacks",
        "watchdog_trips", "solve_us_median", "solve_us_p99",
        "lateness_us_p99", "cycle_us_p99", "drive_ticks", "dsp_faults", "rearms", "arming_ticks",
        "log",
        "rejections", "recorder", "problems",
        "exit_codes", "monitor_error",
    )  # fmt: skip
    print_summary({k: summary.get(k) for k in keys}, args.json, "hil up")
    if summary.get("monitor_error"):
        print(f"hil up: warning: monitor {summary['monitor_error']}", file=sys.stderr)
    problems = summary.get("problems") or []
    if problems:
        print(f"hil up: run not clean: {'; '.join(problems)}", file=sys.stderr)
        return 1
    return 0
