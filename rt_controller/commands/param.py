"""``hil param``: the running controller's online parameters over zenoh (get, set, dump, load,
diff), every request signed with the rig key (:mod:`rt_controller.calibration.link`)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from hal.arguments import MAX_DURATION_S, add_key_option, bounded_float, bounded_int, path_given
from rt_controller.commands.common import add_config_option

ACTION_NAMES = ("arm", "disarm", "mark", "reset_scenario")
"""The operator actions (:data:`rt_controller.calibration.operator.ACTIONS`)."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "param",
        help="get, set, dump, load or diff the running controller's online parameters",
        description="Tune the running controller (gains, law, RHC horizon, timeouts: the keys "
        "of `hil param get`). A change set takes effect at one tick boundary or not at all; "
        "the answer names the tick. Every change, accepted or refused, is in the run's log "
        "(/controller/parameters). dump/load use the config's TOML, so a tuned set is the "
        "next run's --config. arm, disarm and mark (a note in the log's /controller/events) are "
        "operator actions, done at a tick boundary like a change.",
    )
    p.add_argument("action", choices=("get", "set", "dump", "load", "diff", *ACTION_NAMES))
    p.add_argument(
        "items",
        nargs="*",
        metavar="ARG",
        help="get: keys (default all); set: KEY=VALUE (JSON values, else strings); "
        "load/diff: a TOML file (diff: compared with the running set); mark: the note",
    )
    p.add_argument(
        "--at-tick",
        type=bounded_int(0, 2**63 - 1, what="tick"),
        metavar="K",
        help="set/load and the actions: take effect at the first tick >= K",
    )
    p.add_argument(
        "--timeout",
        type=bounded_float(0, MAX_DURATION_S, what="timeout in seconds"),
        metavar="S",
        help="answer wait (default 10 s; with --at-tick 600 s, as the answer comes when that "
        "tick does); also bounds the wait for the zenoh hub (default 10 s)",
    )
    p.add_argument(
        "-o",
        "--out",
        type=path_given,
        metavar="FILE",
        help="dump: write the TOML here (an existing FILE is replaced: dump again to remake it)",
    )
    p.add_argument("--json", action="store_true", help="print the answer as JSON")
    add_config_option(p)
    p.add_argument("--zenoh-endpoint", metavar="tcp/127.0.0.1:PORT", help="loopback endpoint")
    p.add_argument("--zenoh-config", metavar="FILE", help="zenoh json5 config (multi-host)")
    add_key_option(p)
    p.set_defaults(handler=run)


def _values_of_file(path: str) -> dict[str, Any]:
    """The tunable values of the TOML file ``path``, read and validated before any wait for
    the rig (a missing or bad file is named at once, not after a hub timeout)."""
    from hal.config import load_config
    from rt_controller.calibration.parameters import tunable_values

    return tunable_values(load_config(path))


def _changes(wanted: dict[str, Any], running: dict[str, Any]) -> dict[str, Any]:
    """The keys of ``wanted`` whose values differ from ``running``."""
    return {k: v for k, v in wanted.items() if running.get(k) != v}


def _check_keys(keys: list[str]) -> None:
    """Refuse ``get`` of keys that are no online parameter, naming them and the known ones
    (before any wait: ``set`` of such a key is refused too, by the controller)."""
    from rt_controller.calibration.parameters import TUNABLE
    from rt_controller.errors import ControllerConfigError

    unknown = [k for k in keys if k not in TUNABLE]
    if unknown:
        raise ControllerConfigError(
            f"get: unknown parameter key(s) {', '.join(map(repr, unknown))} "
            f"(known: {', '.join(TUNABLE)})"
        )


def run(args: argparse.Namespace) -> int:
    from hal.config import load_config
    from hal.secoc import configure_key, rig_key
    from hal.signals import stop_on_signals
    from hal.zenoh_session import open_session
    from rt_controller.calibration.link import event_line, outcome_line, request
    from rt_controller.commands.output import output_file
    from rt_controller.commands.replay import parse_sets
    from rt_controller.errors import ControllerConfigError

    if args.action == "get":
        _check_keys(args.items)
    cfg = configure_key(load_config(args.config), args.key_file, "hil param")
    if args.action in ("load", "diff") and len(args.items) != 1:
        raise ControllerConfigError(f"hil param {args.action} expects one TOML file")
    wanted = _values_of_file(args.items[0]) if args.action in ("load", "diff") else {}
    changes = parse_sets(args.items, "set") if args.action == "set" else {}
    if args.action == "set" and not changes:
        raise ControllerConfigError("set expects KEY=VALUE ...")
    out_file = None
    if args.out and args.action == "dump":  # a dump is made again from the running set
        out_file = output_file(args.out, "--out", replace=True)
    key = rig_key(cfg)
    hub_wait = {} if args.timeout is None else {"wait_s": args.timeout}
    with stop_on_signals() as stop:
        session = open_session(
            cfg,
            listen=False,
            endpoint=args.zenoh_endpoint,
            config_file=args.zenoh_config,
            stop_event=stop,
            **hub_wait,
        )
        try:

            def ask(op: str, **kw: Any) -> dict[str, Any]:
                return request(session, key, op, timeout_s=args.timeout, **kw)

            if args.action in ACTION_NAMES:
                out = ask(
                    "action",
                    action=args.action,
                    note=" ".join(args.items),
                    at_tick=args.at_tick,
                    source="hil param",
                )
                print(json.dumps(out["event"]) if args.json else f"hil param: {event_line(out)}")
                return 0 if out["event"]["accepted"] else 1
            if args.action == "dump":
                out = ask("dump")
                if out_file is not None:
                    out_file.write_text(out["toml"], encoding="utf-8")
                else:
                    sys.stdout.write(out["toml"])
                return 0
            got = ask("get")
            if args.action == "get":
                values = got["values"]
                shown = {k: values[k] for k in args.items if k in values} if args.items else values
                if args.json:
                    print(json.dumps({"param_set": got["param_set"], "values": shown}))
                else:
                    for k, v in shown.items():
                        print(f"{k} = {json.dumps(v)}")
                return 0
            if args.action == "diff":
                changes = _changes(wanted, got["values"])
                for k, v in changes.items():
                    print(f"{k}: running {json.dumps(got['values'][k])}, file {json.dumps(v)}")
                return 0
            if args.action == "load":
                changes = _changes(wanted, got["values"])
                if not changes:
                    print("hil param: nothing to change", file=sys.stderr)
                    return 0
            out = ask(
                "set", changes=changes, at_tick=args.at_tick, source=f"hil param {args.action}"
            )
        finally:
            session.close()
    if args.json:
        print(json.dumps(out["outcome"]))
    else:
        print(f"hil param: {outcome_line(out)}", file=sys.stderr)
    return 0 if out["outcome"]["accepted"] else 1
