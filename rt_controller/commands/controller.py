"""``hil controller``: the hard-cadence controller daemon (CAN + zenoh + MCAP)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from hal.arguments import add_key_option, duration, path_given
from rt_controller.commands.common import (
    add_config_option,
    add_law_options,
    add_profile_option,
    add_set_option,
    config_from_args,
    rhc_options_note,
)

if TYPE_CHECKING:
    from hal.bus import BusSpec
    from hal.config import RigConfig
    from rt_controller.runtime.daemon import DaemonOptions


def add_transport_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--can",
        metavar="INTERFACE[:CHANNEL]",
        help="CAN bus, e.g. socketcan:can0, pcan:PCAN_USBBUS1, udp_multicast (default: "
        "transport.can = auto: the interface of python-can's configuration, else "
        "socketcan:vcan0 if present, else host-local udp_multicast)",
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
    add_set_option(p)
    add_profile_option(p)
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
    p.add_argument(
        "--log",
        type=path_given,
        metavar="FILE.mcap",
        help="log path (default: logs/run-...mcap); an existing file is refused unless --force",
    )
    p.add_argument("--force", action="store_true", help="replace an existing --log file")
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
    p.add_argument(
        "--plan",
        metavar="FILE.json",
        help="lockstep: run every run of the plan on these links, resetting the emulated "
        "DSP's scenario between runs (one summary per run; see rt_controller/runtime/plan.py); "
        "excludes --law, --duration and --log, which each run gives, and --rate, --horizon, "
        "--steps, --kmax and --zeta, which its config gives",
    )
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from hal.arguments import check_zenoh_options

    check_zenoh_options(args)
    from hal.lean_start import without_scipy_linalg

    without_scipy_linalg()  # before numba: it would import SciPy's BLAS, which no kernel uses
    from rt_controller.runtime.realtime import lean_process

    if not args.no_rt:
        lean_process()  # before the first thread starts (small stacks, few malloc arenas)
    from hal.bus import process_spec
    from hal.secoc import configure_key
    from hal.signals import stop_on_signals
    from rt_controller.commands.output import output_file, print_summary, verdict
    from rt_controller.runtime.daemon import ControllerDaemon

    if args.plan:
        return run_plan_command(args)
    if args.log is not None:  # before the daemon opens its links
        output_file(args.log, "--log", replace=args.force)
    cfg = check_zenoh_config(with_command_line(config_from_args(args), args))
    rhc_options_note(args, cfg, "hil controller")  # kept for a switch to rhc while it runs
    bus = process_spec(cfg.transport.can)  # another process: not python-can's virtual bus
    cfg = configure_key(cfg, args.key_file, "hil controller")
    opts = daemon_options(args)
    with stop_on_signals() as stop:
        daemon = ControllerDaemon(cfg, opts, stop)
        print(
            f"hil controller: law {cfg.controller.law} at {cfg.rates.control_hz:g} Hz "
            f"({cfg.controller.clock}), logging to {daemon.log_path}",
            file=sys.stderr,
        )
        summary = daemon.run()
    print_summary(shown(summary, bus, args.json), args.json, "hil controller")
    return verdict(summary, "hil controller")


def shown(summary: dict, bus: BusSpec, as_json: bool) -> dict:
    """The summary as printed: ``can`` names the bus the run opened (``auto`` resolved, as in
    ``hil up``), and the table shows the counter blocks as ``hil up``'s does."""
    from rt_controller.commands.up import table_view

    out = {**summary, "can": str(bus)} if "can" in summary else summary
    return out if as_json else table_view(out)


def with_command_line(cfg: RigConfig, args: argparse.Namespace) -> RigConfig:
    """``cfg`` with the clock, profile and transport options of the command line (config
    overrides: ``controller.clock``, ``hardware.profile``, ``transport.*``)."""
    from rt_controller.config_rules import apply_overrides

    return apply_overrides(
        cfg,
        clock=args.clock,
        profile=args.profile,
        can=args.can,
        zenoh_endpoint=args.zenoh_endpoint,
        zenoh_config=args.zenoh_config,
        from_command_line=True,
    )


def check_zenoh_config(cfg: RigConfig) -> RigConfig:
    """``cfg`` once its zenoh config file (if any) reads as zenoh's: one that cannot is
    refused before any link, process or log exists."""
    from hal.zenoh_session import load_config_file

    if cfg.transport.zenoh_config:
        load_config_file(cfg.transport.zenoh_config)
    return cfg


def daemon_options(args: argparse.Namespace) -> DaemonOptions:
    """What the command line asks of the run beyond the configuration."""
    from rt_controller.runtime.daemon import DaemonOptions

    return DaemonOptions(
        duration_s=args.duration,
        log_path=Path(args.log) if args.log else None,
        replace_log=args.force,
        realtime_settings=not args.no_rt,
        record_raw=not args.no_raw,
        live=not args.no_live,
        scene=not args.no_scene,
    )


def run_plan_command(args: argparse.Namespace) -> int:
    """``--plan``: every run of the plan, one summary each; 1 when any run was not clean."""
    from hal.bus import process_spec
    from hal.config import load_config
    from hal.secoc import configure_key
    from hal.signals import stop_on_signals
    from rt_controller.commands.common import RHC_ONLY_OPTIONS
    from rt_controller.commands.output import print_summary
    from rt_controller.errors import ControllerConfigError
    from rt_controller.runtime.plan import check_started_seed, load_plan, run_configs, run_plan

    given = [o for o, v in (("--law", args.law), ("--log", args.log)) if v]
    given += ["--duration"] if args.duration else []
    if given:
        raise ControllerConfigError(
            f"--plan gives each run's law, duration and log: drop {', '.join(given)}"
        )
    tuned = [f"--{n}" for n in ("rate", *RHC_ONLY_OPTIONS) if getattr(args, n) is not None]
    if tuned:  # each run's config file is run as it is
        raise ControllerConfigError(
            f"--plan runs each run's config as it is: drop {', '.join(tuned)}"
        )
    runs = load_plan(args.plan)

    def prepare(cfg: RigConfig) -> RigConfig:
        cfg = check_zenoh_config(with_command_line(cfg, args))
        cfg = configure_key(cfg, args.key_file, "hil controller")
        if cfg.controller.clock != "lockstep":
            raise ControllerConfigError(
                "--plan runs lockstep only (a scenario reset rewinds the emulated arm); "
                "set controller.clock = lockstep or pass --clock lockstep"
            )
        if cfg.hardware.profile != "dsp":
            raise ControllerConfigError(
                f"--plan runs on the dsp profile only (the scenario reset between runs is the "
                f"emulated DSP's), not {cfg.hardware.profile}: start the rig for each run "
                "(hil up --lockstep --config RUN.toml)"
            )
        return cfg

    cfgs = run_configs(runs, prepare)
    check_started_seed(runs[0], cfgs[0], load_config(args.config))
    opts = daemon_options(args)
    unclean: list[str] = []
    buses = {run.name: process_spec(c.transport.can) for run, c in zip(runs, cfgs, strict=True)}

    def emit(summary: dict) -> None:
        title = f"hil controller: run {summary['run']}"
        print_summary(shown(summary, buses[summary["run"]], args.json), args.json, title)
        sys.stdout.flush()
        if summary["problems"]:
            unclean.append(f"{summary['run']}: {'; '.join(summary['problems'])}")

    print(f"hil controller: plan of {len(runs)} lockstep runs", file=sys.stderr)
    with stop_on_signals() as stop:
        done = run_plan(runs, cfgs, opts, stop, emit)
    for line in unclean:
        print(f"hil controller: run not clean: {line}", file=sys.stderr)
    if len(done) < len(runs):
        print(f"hil controller: stopped after {len(done)} of {len(runs)} runs", file=sys.stderr)
        return 1
    return 1 if unclean else 0
