"""``hil controller``: the hard-cadence controller daemon (CAN + zenoh + MCAP)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hal.arguments import add_key_option, duration
from rt_controller.commands.common import add_config_option, add_law_options, config_from_args


def add_transport_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--can",
        metavar="INTERFACE[:CHANNEL]",
        help="CAN bus, e.g. socketcan:vcan0, udp_multicast, virtual (default: transport.can = "
        "auto: socketcan:vcan0 if present, else host-local udp_multicast)",
    )
    p.add_argument("--zenoh-endpoint", metavar="tcp/127.0.0.1:PORT", help="loopback endpoint")
    p.add_argument("--zenoh-config", metavar="FILE", help="zenoh json5 config (multi-host)")
    add_key_option(p)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "controller",
        help="run the controller daemon against the DSP (CAN) and vision (zenoh)",
        description="Hard-cadence control loop: read joint state and features, run the law, "
        "send tau (eq. 11), log every cycle to MCAP. SIGTERM/SIGINT: torque off, log finished.",
    )
    add_law_options(p)
    add_config_option(p)
    add_transport_options(p)
    p.add_argument(
        "--clock",
        choices=("realtime", "lockstep"),
        help="realtime (monotonic deadlines) or lockstep (tick on the DSP's Sync frames); "
        "default: controller.clock",
    )
    p.add_argument(
        "--duration",
        type=duration(zero_means_forever=True),
        default=0.0,
        metavar="S",
        help="0 = until stopped",
    )
    p.add_argument("--log", metavar="FILE.mcap", help="log path (default: logs/run-...mcap)")
    p.add_argument(
        "--no-rt", action="store_true", help="skip SCHED_FIFO/mlockall/affinity settings"
    )
    p.add_argument("--no-raw", action="store_true", help="do not record raw CAN/vision inputs")
    p.add_argument(
        "--no-live",
        action="store_true",
        help="do not publish cycles/diagnostics on zenoh hil/controller/* (for hil monitor)",
    )
    p.add_argument("--no-scene", action="store_true", help="do not draw the arm into the log")
    p.add_argument("--json", action="store_true", help="print the run summary as one JSON object")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from hal.lean_start import without_scipy_linalg

    without_scipy_linalg()  # before numba: it would import SciPy's BLAS, which no kernel uses
    from rt_controller.runtime.realtime import lean_process

    if not args.no_rt:
        lean_process()  # before the first thread starts (small stacks, few malloc arenas)
    from hal.secoc import configure_key
    from hal.signals import stop_on_signals
    from rt_controller.commands.output import print_summary
    from rt_controller.runtime.daemon import ControllerDaemon, DaemonOptions

    cfg = configure_key(config_from_args(args), args.key_file, "hil controller")
    if args.clock:
        cfg = cfg.with_overrides({"controller.clock": args.clock})
    opts = DaemonOptions(
        can=args.can,
        lockstep=cfg.controller.clock == "lockstep",
        duration_s=args.duration,
        log_path=Path(args.log) if args.log else None,
        zenoh_endpoint=args.zenoh_endpoint,
        zenoh_config=args.zenoh_config,
        realtime_settings=not args.no_rt,
        record_raw=not args.no_raw,
        live=not args.no_live,
        scene=not args.no_scene,
    )
    with stop_on_signals() as stop:
        daemon = ControllerDaemon(cfg, opts, stop)
        print(
            f"hil controller: law {cfg.controller.law} at {cfg.rates.control_hz:g} Hz "
            f"({cfg.controller.clock}), logging to {daemon.log_path}",
            file=sys.stderr,
        )
        summary = daemon.run()
    print_summary(summary, args.json, "hil controller")
    if summary["problems"]:
        print(f"hil controller: run not clean: {'; '.join(summary['problems'])}", file=sys.stderr)
        return 1
    return 0
