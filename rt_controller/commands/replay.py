"""``hil replay``: re-run the controller offline on a log and compare, or republish its inputs."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hal.arguments import MAX_DURATION_S, bounded_float, path_given
from hal.config import RigConfig
from rt_controller.commands.common import add_set_option
from rt_controller.commands.interrupts import run_interruptible, unwritten
from rt_controller.commands.progress import Progress, add_quiet_option
from rt_controller.config_rules import apply_overrides, parse_sets

DESCRIPTION = """\
Re-run the controller offline on the inputs recorded in LOG.mcap (per tick: sim_time_s, q, dq,
f, f_stale, state_stale as received) with the configuration stored in the log, and compare its
u and tau with the recorded ones. Exit 0 when every component is within --tol, 1 when not (one
line on stderr: "replay differs from the log: max |dtau| = ... at tick ... (tol ...)"), 2 for a
bad file or option. A truncated or damaged log is replayed as far as it goes, with a note, and
fails (exit 1, "log is incomplete or damaged: ...") unless --allow-partial.

The replay compiles the law for the CPU target the log records (numba's CPU name and features,
in hil.run): when that is not this process's and this host can run it, in a new process with
that target's own numba cache, saying so in one line. When this host cannot run it (or the log
predates the record) and the replay is over --tol, the log is replayed once more for a second
target (generic) and the difference between the two is the cross-target spread on this log: a
difference from the log up to 10 times that spread is the compile target's (exit 0, both
figures in compile_target); more is a change (exit 1, with the spread in the line).

--config FILE replaces the log's configuration; --set KEY=VALUE (repeatable, VALUE parsed as
JSON, else taken as a string) changes single settings on top, e.g. --set gains.kp=0.2 or
--set rhc.kmax=8: the regression check of a changed solver against yesterday's rig run.
--out NEW.mcap writes the replayed run (replayed u/tau, zero loop-timing fields); an existing
NEW.mcap is refused unless --force (the log being replayed, never).
--json keys: log, law, ticks, max_abs_du, max_abs_dtau, worst_tick, worst_tick_du,
worst_tick_dtau, ticks_over_tol, law_mismatches, tol, ok, matches, truncated, allow_partial,
skipped_records (cycle records that could not be read: the log is damaged), compile_target,
cross_target_spread, within_spread (null when no spread was measured), notes (and out).

--republish plays the recorded raw inputs back instead: the /hal/can/rx frames onto CAN (raw,
original E2E counters and CRCs) and the /vision/features payloads onto zenoh (realtime messages
re-stamped so they arrive as old as they were recorded), at the recorded timing divided by
--speed (0 = as fast as possible), so a live `hil controller` can be fed a recorded run.
"""


SECONDS = bounded_float(0, MAX_DURATION_S, lo_inclusive=True, what="seconds")
"""A wait of the republisher: 0 or more, finite."""


def register(sub: argparse._SubParsersAction) -> None:
    from rt_controller.commands.controller import add_transport_options

    p = sub.add_parser(
        "replay",
        help="re-run the controller on a log and compare u/tau, or --republish its inputs",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("log", metavar="LOG.mcap", help="controller log")
    p.add_argument(
        "--tol", type=float, default=1e-9, help="largest |difference| counted as equal (1e-9)"
    )
    p.add_argument(
        "--out", type=path_given, metavar="NEW.mcap", help="write the replayed run to this log"
    )
    p.add_argument("--force", action="store_true", help="replace an existing --out file")
    p.add_argument(
        "--allow-partial",
        action="store_true",
        help="accept a truncated or damaged log (replayed as far as it goes) as a success",
    )
    p.add_argument("--config", metavar="FILE", help="configuration replacing the log's (TOML)")
    add_set_option(p)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    add_quiet_option(p)
    g = p.add_argument_group("republish")
    g.add_argument(
        "--republish", action="store_true", help="play the raw inputs onto CAN and zenoh"
    )
    g.add_argument(
        "--speed",
        type=bounded_float(0, 1e6, lo_inclusive=True, what="speed factor"),
        default=1.0,
        help="playback speed factor (0 = as fast as possible)",
    )
    g.add_argument(
        "--wait-subscriber",
        type=SECONDS,
        default=10.0,
        metavar="S",
        help="wait up to S s for a features subscriber before playing (default 10; 0 = no)",
    )
    g.add_argument(
        "--lead-in",
        type=SECONDS,
        default=0.5,
        metavar="S",
        help="pause S s after the subscriber appeared before the first message (default 0.5)",
    )
    add_transport_options(g)
    p.set_defaults(handler=run)


def _config(args: argparse.Namespace, log_cfg: RigConfig | None) -> RigConfig | None:
    """The override configuration (None: the log's own, unchanged)."""
    from hal.config import load_config

    sets = parse_sets(args.sets)
    base = load_config(args.config) if args.config else log_cfg
    if not sets:
        return base if args.config else None
    if base is None:
        base = load_config()
    return apply_overrides(base, sets=sets, from_command_line=True)


def run(args: argparse.Namespace) -> int:
    if args.republish:
        return _run(args)
    out = Path(args.out) if args.out else None
    existed = out is not None and out.exists()
    state = {"done": False}

    def left() -> str:
        if out is None:
            return "nothing was written"
        if state["done"]:
            return f"--out {out} was written whole"
        return f"--out {unwritten(out, existed)}"

    return run_interruptible("hil replay", lambda: _run(args, state), left)


def _run(args: argparse.Namespace, state: dict[str, bool] | None = None) -> int:
    """The command; ``state["done"]`` is set once the replay (and its --out) is complete."""
    from rt_controller.commands.output import print_summary_with_notes

    if args.republish:
        if args.out:
            from rt_controller.errors import ControllerConfigError

            raise ControllerConfigError("--out writes a replayed run; --republish writes none")
        return _republish(args)
    from rt_controller.commands.output import output_file
    from rt_controller.logtools.reader import read_hil_log, same_file
    from rt_controller.logtools.target_replay import replay_as_recorded

    parse_sets(args.sets)  # a malformed or repeated --set is told before the log is read
    out = None
    if args.out:  # the log itself is refused by the replay, whatever --force says
        replace = args.force or same_file(args.out, args.log)
        out = output_file(args.out, "--out", replace=replace)
    progress = Progress.of(args, "hil replay")
    with progress.stage(f"reading {args.log}"):
        log = read_hil_log(args.log, raw=out is not None)
    cfg = _config(args, log.config)
    run_cfg = cfg or log.config
    law = run_cfg.controller.law if run_cfg is not None else "the law of --config"
    with progress.stage(
        f"replaying {log.n_cycles} ticks with {law} (numba compiles on a cold cache)"
    ):
        result = replay_as_recorded(
            log,
            cfg_override=cfg,
            tol=args.tol,
            out=out,
            allow_partial=args.allow_partial,
            say=progress.line,
        )
    if state is not None:
        state["done"] = True
    print_summary_with_notes(result.as_dict(), args.json, f"hil replay {args.log}")
    if not result.ok:
        print(f"hil replay: {result.failure_line()}", file=sys.stderr)
        return 1
    return 0


def _republish(args: argparse.Namespace) -> int:
    from hal.config import RigConfig, load_config
    from hal.secoc import configure_key, rig_key
    from hal.signals import stop_on_signals
    from rt_controller.commands.output import print_summary_with_notes
    from rt_controller.logtools.reader import read_hil_log
    from rt_controller.logtools.republish import republish_log

    log = read_hil_log(args.log, raw=False)
    cfg = _config(args, log.config) if args.config or args.sets else None
    # the live rig's key, never the recorded run's
    live = load_config(args.config) if args.config else RigConfig()
    key = rig_key(configure_key(live, args.key_file, "hil replay --republish"))
    with stop_on_signals() as stop:
        result = republish_log(
            args.log,
            speed=args.speed,
            can_spec=args.can,
            zenoh_endpoint=args.zenoh_endpoint,
            zenoh_config=args.zenoh_config,
            cfg=cfg,
            wait_subscriber_s=args.wait_subscriber,
            lead_in_s=args.lead_in,
            stop=stop,
            key=key,
        )
    print_summary_with_notes(result.as_dict(), args.json, f"hil replay --republish {args.log}")
    return 0
