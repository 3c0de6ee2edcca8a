"""``hil up``: emulator, vision and controller as separate processes, one summary."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hal.arguments import bounded_int, duration, path_given
from rt_controller.commands.common import (
    add_law_options,
    add_profile_option,
    add_scenario_options,
    add_set_option,
)

RIG_OWN = {"transport.zenoh_endpoint": "--zenoh-endpoint", "transport.key_file": "--key-file"}
"""Keys ``hil up`` sets for the rig it starts (a free port, a fresh key): a ``--set`` of one is
refused, naming the option that does it."""

SUMMARY_KEYS = (
    "clock", "rate_hz", "duration_s", "law", "horizon_s", "steps", "can",
    "ticks", "planned_ticks", "end_reason", "stop_signal", "J", "f_first", "jump_seen_s",
    "f_final", "f_final_norm", "deadline_misses", "missed_periods", "stale_features",
    "stale_states", "late_states", "fallbacks", "watchdog_trips", "solve_us_median",
    "solve_us_p99", "lateness_us_p99", "cycle_us_p99", "host_steal_percent", "drive_ticks",
    "dsp_faults", "rearms", "arming_ticks", "ended_by", "dsp", "log", "log_contents",
    "rejections", "recorder", "outages", "problems", "warnings", "exit_codes", "stderr_tail",
    "monitor_error",
)  # fmt: skip
"""What ``hil up`` prints of the controller's summary, in this order."""
NONZERO_ONLY = ("input_counts", "rejections", "recorder")
"""Counter blocks of which the table shows only the counters that are not zero (``--json``
has them all)."""
NOT_REJECTIONS = frozenset(
    {
        "accepted", "received", "ignored", "lost", "invalid", "repeats", "source_changes",
        "resyncs", "resent", "images_missing", "images_of_run_before", "callback_errors",
        "syncs_sent", "drains_cut", "foreign_stamps",
    }
)  # fmt: skip
"""The counters of the summary's ``rejections`` block that count no rejection: frames and
messages accepted or received (:class:`hal.e2e.E2EStats`, the feature link's counters), and
what the link saw besides (frames lost in counter gaps, accepted repeats, resyncs, images
missing..., a cia402 master's SYNCs sent). The table shows them as ``input_counts``,
``rejections`` only the rest."""
WRITTEN_WORDS = "written {} (the topics listed; the writer's /scene, /camera, /tf not counted)"
"""The recorder's ``written`` in the table: the messages of the topics it lists, which the
controller handed to the writer, not every message of the log (``hil info`` counts those)."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "up",
        help="start emulator, vision and controller, run the paper scenario, stop, summarise",
        description="Starts `hil emulator`, `hil vision` and `hil controller` as separate "
        "processes on the embedded defaults, waits --duration, stops them cleanly and prints "
        "final |f|, J, deadline misses, solve time and the log path.",
    )
    add_law_options(p)
    add_scenario_options(p)
    p.add_argument("--duration", type=duration(), default=10.0, metavar="S", help="default 10")
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="DSP clocks the run with Sync frames: deterministic, faster than real time "
        "(default: controller.clock of the config)",
    )
    p.add_argument(
        "--wall-timeout",
        type=duration(),
        metavar="S",
        help="wall-clock seconds before the run is called hung (default: duration + 60 s; "
        "lockstep: 20 x duration + 60 s)",
    )
    p.add_argument("--can", metavar="INTERFACE[:CHANNEL]", help="CAN bus (default: auto)")
    add_profile_option(p)
    p.add_argument("--config", metavar="FILE", help="rig configuration (TOML)")
    add_set_option(p)
    p.add_argument(
        "--log",
        type=path_given,
        metavar="FILE.mcap",
        help="controller log path (an existing file is refused unless --force)",
    )
    p.add_argument("--force", action="store_true", help="replace an existing --log file")
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
    p.add_argument(
        "--monitor-port",
        type=bounded_int(0, 65535, what="port"),
        metavar="PORT",
        help="live view port (8765; 0 = any free one); implies --monitor. hil up says the "
        "live view's address on stderr as it starts",
    )
    p.add_argument(
        "--allow-tuning",
        action="store_true",
        help="with --monitor (refused without it): Foxglove may set the tunable parameters and "
        "call the operator services (hil monitor --allow-tuning); off: read-only",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from hal.bus import process_spec
    from rt_controller.commands.common import config_from_args, rhc_options_note
    from rt_controller.commands.output import output_file, verdict
    from rt_controller.control.simulate import tick_count, too_short
    from rt_controller.errors import ControllerConfigError
    from rt_controller.rig.failures import RigHung
    from rt_controller.rig.options import RigOptions, emulator_bus_warning
    from rt_controller.rig.processes import run_rig
    from rt_controller.rig.scratch import private_folder
    from rt_controller.rig.supervise import RigInterrupted, supervised

    if args.allow_tuning and not (args.monitor or args.monitor_port is not None):
        raise ControllerConfigError(
            "--allow-tuning opens the live view to tuning: it needs --monitor (or --monitor-port)"
        )
    if args.log is not None:
        # checked once, here: the rig tells its controller to replace (rig/processes.py)
        output_file(args.log, "--log", replace=args.force)
    config = _effective_config(args)
    cfg = config_from_args(args)
    rhc_options_note(args, cfg, "hil up")  # kept for a switch to rhc while it runs
    bus = process_spec(args.can or cfg.transport.can)  # three processes: not python-can's virtual
    if (warning := emulator_bus_warning(bus)) is not None:
        print(f"hil up: warning: {warning}", file=sys.stderr)
    rate = cfg.rates.control_hz
    if tick_count(args.duration, rate) < 1:  # a run of no tick is no run, not a clean one
        raise ControllerConfigError(too_short(args.duration, rate))
    monitor = args.monitor or args.monitor_port is not None
    port = _check_monitor_port(args.monitor_port) if monitor else None
    with private_folder("hil-up-") as tmp:
        if config is not None:  # the command-line overrides reach all three processes
            conf = tmp / "rig.toml"
            conf.write_text(config, encoding="utf-8")
        if monitor:  # the live view is for during the run: say where it is now
            print(f"hil up: live view on ws://127.0.0.1:{port} (Foxglove)", file=sys.stderr)
        try:
            with supervised():
                summary = run_rig(
                    RigOptions(
                        config=str(conf) if config is not None else args.config,
                        law=args.law,
                        duration_s=args.duration,
                        # as each process takes it: the flag, else the config's clock
                        lockstep=args.lockstep or cfg.controller.clock == "lockstep",
                        wall_timeout_s=args.wall_timeout,
                        can=args.can,
                        zenoh_endpoint=args.zenoh_endpoint,
                        log=Path(args.log) if args.log else None,
                        replace_log=args.force,
                        monitor=monitor,
                        monitor_port=port,
                        extra_monitor=["--allow-tuning"] if args.allow_tuning else [],
                        key_file=Path(args.key_file) if args.key_file else None,
                    )
                )
        except RigInterrupted as exc:
            _print(exc.summary, args.json)
            print(
                f"hil up: {exc}: stopped the rig (controller first), nothing left running",
                file=sys.stderr,
            )
            return exc.exit_code
        except RigHung as exc:
            summary = dict(exc.summary or {})
            summary["problems"] = [f"hung: {exc}", *summary.get("problems", [])]
    _print(summary, args.json)
    if summary.get("monitor_error"):
        print(f"hil up: warning: monitor {summary['monitor_error']}", file=sys.stderr)
    return verdict(summary, "hil up")


def _print(summary: dict | None, as_json: bool) -> None:
    """The summary (what was run first), if the controller gave one."""
    from rt_controller.commands.output import print_summary

    if summary and "ticks" in summary:
        shown = {k: summary.get(k) for k in SUMMARY_KEYS if k in summary or as_json}
        print_summary(shown if as_json else table_view(shown), as_json, "hil up")
    elif summary:  # a hang before the controller said anything: only why
        print_summary(summary, as_json, "hil up")


def table_view(summary: dict) -> dict:
    """The summary as the table shows it: of :data:`NONZERO_ONLY` only the counters that are
    not zero (nested blocks flattened to ``block.key``), the DSP's watchdog account, the
    log's contents and the outages in words, every other block as ``accepted 2, refused 0``
    (``none`` when empty), a None as :func:`none_words` says: never a Python dict or None."""
    from rt_controller.rig.ending import contents_words, dsp_words, end_words

    out = dict(summary)
    if out.get("stop_signal"):
        out["end_reason"] = end_words(out)  # "stopped by SIGINT"
        out.pop("stop_signal")
    if isinstance(out.get("rejections"), dict):
        out = split_rejections(out)
    for key in NONZERO_ONLY:
        if isinstance(out.get(key), dict):
            counts = nonzero(out[key])
            words = [f"{k} {v}" for k, v in counts.items()]
            if key == "recorder" and "written" in counts:
                words[list(counts).index("written")] = WRITTEN_WORDS.format(counts["written"])
            out[key] = ", ".join(words) or "none"
    if isinstance(out.get("dsp"), dict):
        out["dsp"] = dsp_words(out["dsp"])
    if isinstance(out.get("log_contents"), dict):
        out["log_contents"] = contents_words(out["log_contents"])
    if isinstance(out.get("ended_by"), dict):
        out.pop("ended_by")  # end_reason says it in words
    if isinstance(out.get("outages"), dict):
        o = out["outages"]
        out["outages"] = f"{o.get('count', 0)} (longest {o.get('longest_ticks', 0)} ticks)"
    for key, value in out.items():  # every other block (drive_ticks, parameters, ...)
        if isinstance(value, dict):
            out[key] = ", ".join(f"{k} {v}" for k, v in flat(value).items()) or "none"
        elif value is None:  # never a Python None: what it means
            out[key] = none_words(key, out)
    return out


def split_rejections(summary: dict) -> dict:
    """``summary`` with its ``rejections`` block split in two: the counters of
    :data:`NOT_REJECTIONS` (by their last name: ``can_rx.accepted``) as ``input_counts``, placed
    before ``rejections``, which keeps the others."""
    block = flat(summary["rejections"])
    inputs = {k: v for k, v in block.items() if k.rsplit(".", 1)[-1] in NOT_REJECTIONS}
    out: dict = {}
    for key, value in summary.items():
        if key == "rejections":
            out["input_counts"] = inputs
            value = {k: v for k, v in block.items() if k not in inputs}
        out[key] = value
    return out


def none_words(key: str, summary: dict) -> str:
    """What a figure of None means in the table: ``not seen`` for the target's jump, ``n/a``
    (and why, where known) for a figure that does not apply to the run, ``-`` otherwise."""
    if key == "jump_seen_s":
        return "not seen"
    if key in ("horizon_s", "steps") and summary.get("law") not in (None, "rhc"):
        return f"n/a (law {summary['law']}, not rhc)"
    if key == "host_steal_percent":
        return "n/a (lockstep)" if summary.get("clock") == "lockstep" else "n/a"
    return "-"


def flat(counts: dict, prefix: str = "") -> dict:
    """``counts`` with nested dicts flattened to dotted keys:
    ``{"can_rx": {"crc": 2, "ok": 0}}`` -> ``{"can_rx.crc": 2, "can_rx.ok": 0}``."""
    out: dict = {}
    for key, value in counts.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flat(value, f"{name}."))
        else:
            out[name] = value
    return out


def nonzero(counts: dict, prefix: str = "") -> dict:
    """The counters of ``counts`` that are not zero (or empty), nested dicts flattened to
    dotted keys: ``{"can_rx": {"crc": 2, "ok": 0}}`` -> ``{"can_rx.crc": 2}``."""
    zero = (0, None, False, "", [], 0.0)
    return {k: v for k, v in flat(counts, prefix).items() if v not in zero}


def _effective_config(args: argparse.Namespace) -> str | None:
    """The config with the command-line overrides (validated now: a bad value is refused
    before any process starts), as TOML; None when nothing is overridden."""
    from rt_controller.commands.common import config_from_args
    from rt_controller.config_rules import config_toml
    from rt_controller.errors import ControllerConfigError

    for key, option in RIG_OWN.items():
        if any(item.partition("=")[0].strip() == key for item in args.sets):
            raise ControllerConfigError(f"--set {key}: hil up sets it for its rig; use {option}")
    cfg = config_from_args(args)
    names = ("rate", "horizon", "steps", "kmax", "zeta", "seed", "profile")
    if all(getattr(args, n) is None for n in names) and not (args.no_disturbance or args.sets):
        return None
    return config_toml(cfg, header="hil up: the config with its command-line overrides")


def _check_monitor_port(port: int | None) -> int:
    """The live view's port: refused before the rig starts when it cannot be opened; for 0
    (any), a free port picked now, so that ``hil up`` can say where the live view is."""
    import socket

    from rt_controller.errors import ControllerConfigError
    from rt_controller.monitor.bridge import DEFAULT_PORT

    port = DEFAULT_PORT if port is None else port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        # as the monitor's server binds (tokio sets it): a closed client connection's
        # TIME_WAIT must not refuse the port for a minute, a listener still does
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(("127.0.0.1", port))
            sock.listen(1)
        except OSError as exc:
            raise ControllerConfigError(
                f"--monitor: cannot listen on 127.0.0.1:{port}: {exc.strerror or exc} (another "
                "rig's live view?); choose another with --monitor-port PORT (0 = any)"
            ) from None
        return int(sock.getsockname()[1])
