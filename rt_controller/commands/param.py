"""``hil param``: the running controller's online parameters over zenoh (get, set, dump, load,
diff), every request signed with the rig key (:mod:`rt_controller.calibration.link`)."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

from hal import strict_json
from hal.arguments import MAX_DURATION_S, add_key_option, bounded_float, bounded_int, path_given
from hal.signals import signal_name_of
from rt_controller.commands.common import add_config_option

if TYPE_CHECKING:
    from hal.config import RigConfig

ACTION_NAMES = ("arm", "disarm", "mark", "reset_scenario")
"""The operator actions (:data:`rt_controller.calibration.operator.ACTIONS`)."""
T = TypeVar("T")


class Interrupted(Exception):
    """Ctrl-C or SIGTERM while a request waited for its answer: :attr:`status` 130 or 143."""

    def __init__(self, line: str, status: int) -> None:
        super().__init__(line)
        self.status = status


def _until_stopped(stop: threading.Event, op: str, call: Callable[[], T]) -> T:
    """``call()`` (one request) in a worker thread while this one waits for it or for ``stop``:
    zenoh's wait for an answer (up to 600 s for a set at a later tick) takes no signal, so
    Ctrl-C would otherwise go unheeded until it ends. :class:`Interrupted` when stopped."""
    box: dict[str, Any] = {}
    done = threading.Event()

    def work() -> None:
        try:
            box["out"] = call()
        except BaseException as exc:  # handed to the waiting thread
            box["exc"] = exc
        finally:
            done.set()

    threading.Thread(target=work, name="hil-param-request", daemon=True).start()
    while not done.wait(0.05):
        if stop.is_set():
            name = signal_name_of(stop) or "SIGINT"
            line = f"interrupted by {name} before the answer"
            if op in ("set", "action"):
                line += f"; the {op} was sent and may still take effect (the run's log says)"
            raise Interrupted(line, 128 + signal.Signals[name])
    if "exc" in box:
        raise box["exc"]
    return box["out"]


def hub_wait_interrupted(stop: threading.Event, endpoint: str) -> Interrupted:
    """The :class:`Interrupted` of a signal that ended the wait for the zenoh hub at
    ``endpoint`` (:class:`hal.errors.HalStopped` from ``open_session``): no rig there yet."""
    name = signal_name_of(stop) or "SIGINT"
    line = f"interrupted by {name} while waiting for the zenoh hub at {endpoint} (no rig there yet)"
    return Interrupted(line, 128 + signal.Signals[name])


def open_hub_session(
    args: argparse.Namespace, cfg: RigConfig, stop: threading.Event, **hub_wait: float
) -> Any:
    """A live tool's zenoh session (``--zenoh-endpoint``/``--zenoh-config``), waiting for the
    rig's hub; :class:`Interrupted` when a signal ends the wait."""
    from hal.arguments import check_zenoh_options
    from hal.errors import HalStopped
    from hal.zenoh_session import open_session

    check_zenoh_options(args)
    try:
        return open_session(
            cfg,
            listen=False,
            endpoint=args.zenoh_endpoint,
            config_file=args.zenoh_config,
            stop_event=stop,
            **hub_wait,
        )
    except HalStopped:  # Ctrl-C before the hub came: an interruption, not bad args
        raise hub_wait_interrupted(stop, hub_endpoint(args, cfg)) from None


def hub_endpoint(args: argparse.Namespace, cfg: RigConfig) -> str:
    """The loopback endpoint ``open_session`` waits on for these ``args`` and ``cfg``."""
    from hal.zenoh_session import DEFAULT_ENDPOINT

    return args.zenoh_endpoint or cfg.transport.zenoh_endpoint or DEFAULT_ENDPOINT


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


def _file_settings(path: str) -> tuple[RigConfig, set[str]]:
    """The TOML file ``path`` as a validated config and the dotted keys it sets, read before
    any wait for the rig (a missing or bad file is named at once, not after a hub timeout).
    Only the keys it sets are loaded: a key it leaves out keeps its running value, not the
    embedded default (a partial file must not switch the law of a rig started with --law)."""
    import tomllib

    from hal.config import load_config, read_text_file

    cfg = load_config(path)
    data = tomllib.loads(read_text_file(path, "config file"))
    return cfg, {f"{s}.{k}" for s, body in data.items() if isinstance(body, dict) for k in body}


def _not_online(path: str, file_cfg: RigConfig, keys: set[str], dump_toml: str) -> str | None:
    """A note naming the keys ``path`` sets to other values than the running configuration
    (``dump_toml``) that no online change can apply (None: there are none)."""
    import tomllib

    from hal.config import config_from_dict
    from rt_controller.calibration.parameters import TUNABLE, diff

    running = config_from_dict(tomllib.loads(dump_toml), source="the controller's dump")
    apart = {k: v for k, v in diff(running, file_cfg).items() if k in keys and k not in TUNABLE}
    if not apart:
        return None
    items = ", ".join(
        f"{k} (running {json.dumps(a)}, file {json.dumps(b)})" for k, (a, b) in apart.items()
    )
    return (
        f"{path} sets keys that are no online parameter, left as they run (restart with "
        f"--config to change them): {items}"
    )


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


def _check_options(args: argparse.Namespace) -> None:
    """Refuse an option or ARG that ``args.action`` would ignore (a dump "to" FILE that
    goes to stdout, a get "at" a tick that reads now), before any wait for the rig."""
    from rt_controller.errors import ControllerConfigError

    act = args.action
    if args.out and act != "dump":
        raise ControllerConfigError(f"{act}: -o/--out is for dump only")
    if args.at_tick is not None and act in ("get", "dump", "diff"):
        raise ControllerConfigError(f"{act}: --at-tick is for set, load and the actions only")
    if args.json and act == "dump":
        raise ControllerConfigError("dump: --json does not apply: a dump is the config's TOML")
    if act == "dump" and args.items:
        raise ControllerConfigError(f"dump takes no ARG, got {args.items[0]!r} (write to FILE: -o)")


def _print_diff(changes: dict[str, Any], got: dict[str, Any], as_json: bool) -> None:
    """The tunable keys whose file value differs from the running one, as lines or as one
    JSON object ``{"param_set", "differ": {key: {"running", "file"}}}``."""
    running = got["values"]
    if as_json:
        differ = {k: {"running": running[k], "file": v} for k, v in changes.items()}
        print(strict_json.dumps({"param_set": got["param_set"], "differ": differ}))
        return
    for k, v in changes.items():
        print(f"{k}: running {json.dumps(running[k])}, file {json.dumps(v)}")


def run(args: argparse.Namespace) -> int:
    try:
        return _run(args)
    except Interrupted as exc:
        print(f"hil param: {exc}", file=sys.stderr)
        return exc.status


def _run(args: argparse.Namespace) -> int:
    from hal.config import load_config
    from hal.secoc import configure_key, rig_key
    from hal.signals import stop_on_signals
    from rt_controller.calibration.link import event_line, outcome_line, request
    from rt_controller.calibration.parameters import TUNABLE, value_of
    from rt_controller.commands.output import output_file
    from rt_controller.config_rules import parse_sets
    from rt_controller.errors import ControllerConfigError

    _check_options(args)
    if args.action == "get":
        _check_keys(args.items)
    cfg = configure_key(load_config(args.config), args.key_file, "hil param")
    if args.action in ("load", "diff") and len(args.items) != 1:
        raise ControllerConfigError(f"hil param {args.action} expects one TOML file")
    file_cfg, file_keys = None, set()
    if args.action in ("load", "diff"):
        file_cfg, file_keys = _file_settings(args.items[0])
    wanted = {k: value_of(file_cfg, k) for k in TUNABLE if k in file_keys}
    changes = parse_sets(args.items, "set") if args.action == "set" else {}
    if args.action == "set" and not changes:
        raise ControllerConfigError("set expects KEY=VALUE ...")
    out_file = None
    if args.out:  # a dump is made again from the running set
        out_file = output_file(args.out, "--out", replace=True)
    key = rig_key(cfg)
    hub_wait = {} if args.timeout is None else {"wait_s": args.timeout}
    with stop_on_signals() as stop:
        session = open_hub_session(args, cfg, stop, **hub_wait)
        try:

            def ask(op: str, **kw: Any) -> dict[str, Any]:
                return _until_stopped(
                    stop, op, lambda: request(session, key, op, timeout_s=args.timeout, **kw)
                )

            if args.action in ACTION_NAMES:
                out = ask(
                    "action",
                    action=args.action,
                    note=" ".join(args.items),
                    at_tick=args.at_tick,
                    source="hil param",
                )
                print(
                    strict_json.dumps(out["event"])
                    if args.json
                    else f"hil param: {event_line(out)}"
                )
                return 0 if out["event"]["accepted"] else 1
            if args.action == "dump":
                out = ask("dump")
                if out_file is not None:
                    out_file.write_text(out["toml"], encoding="utf-8")
                else:
                    sys.stdout.write(out["toml"])
                return 0
            if file_cfg is not None and file_keys - TUNABLE.keys():
                note = _not_online(args.items[0], file_cfg, file_keys, ask("dump")["toml"])
                if note is not None:
                    print(f"hil param: {note}", file=sys.stderr)
            got = ask("get")
            if args.action == "get":
                values = got["values"]
                shown = {k: values[k] for k in args.items if k in values} if args.items else values
                if args.json:
                    print(strict_json.dumps({"param_set": got["param_set"], "values": shown}))
                else:
                    for k, v in shown.items():
                        print(f"{k} = {json.dumps(v)}")
                return 0
            if args.action == "diff":
                _print_diff(_changes(wanted, got["values"]), got, args.json)
                return 0
            if args.action == "load":
                changes = _changes(wanted, got["values"])
                if not changes:  # nothing sent: no outcome, but --json still prints one object
                    print("hil param: nothing to change", file=sys.stderr)
                    if args.json:
                        print(strict_json.dumps({"param_set": got["param_set"], "changes": []}))
                    return 0
            out = ask(
                "set", changes=changes, at_tick=args.at_tick, source=f"hil param {args.action}"
            )
        finally:
            session.close()
    if args.json:
        print(strict_json.dumps(out["outcome"]))
    else:
        print(f"hil param: {outcome_line(out)}", file=sys.stderr)
    return 0 if out["outcome"]["accepted"] else 1
