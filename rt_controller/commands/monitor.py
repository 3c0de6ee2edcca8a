"""``hil monitor``: the running rig in Foxglove (or Lichtblick) over a Foxglove WebSocket."""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

from hal import strict_json
from hal.arguments import add_key_option, bounded_int, duration
from hal.signals import wait_for_stop
from rt_controller.commands.common import add_config_option

HUB_NOTE_S = 1.0
"""After this long without the zenoh hub, ``hil monitor`` says it waits for it (when its wait
may last at least twice as long: a shorter one ends with its error soon enough)."""
SILENT_S = 3.0
"""No cycle or diagnostics record for this long after some came: said (the rig went silent)."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "monitor",
        help="bridge the rig's zenoh streams to a Foxglove WebSocket server (live view)",
        description="Subscribes to hil/controller/cycle, hil/controller/diagnostics, the "
        "features and the emulator's camera pose, and serves them with foxglove-sdk: the cycle "
        "topic with its JSON Schema (the plots of foxglove/layout.json work live) and the arm, "
        "camera, target and image features drawn with Foxglove's schemas. Open Foxglove -> "
        "Open connection -> Foxglove WebSocket -> ws://127.0.0.1:8765. The tunable parameters "
        "are advertised (Parameters capability) and reach the controller over the rig-key-signed "
        "link of hil param; setting them needs --allow-tuning. Another host may watch with "
        "--allow-remote (read-only); tuning from another host needs TLS (--tls-cert, --tls-key: "
        "wss://) and the access token (--print-token), which a client sets as the parameter "
        "hil.token before it may change anything. Runs until SIGTERM/SIGINT or --duration; "
        "says on stderr when it waits for the zenoh hub and when the rig stops sending.",
    )
    add_config_option(p)
    p.add_argument("--zenoh-endpoint", metavar="tcp/127.0.0.1:PORT", help="loopback endpoint")
    p.add_argument("--zenoh-config", metavar="FILE", help="zenoh json5 config (multi-host)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1)")
    p.add_argument(
        "--port",
        type=bounded_int(0, 65535, what="port"),
        default=8765,
        help="WebSocket port (default 8765; 0 = any)",
    )
    p.add_argument(
        "--allow-remote",
        action="store_true",
        help="allow a --host that is not a loopback address: a read-only view, or with "
        "--allow-tuning over TLS with the access token",
    )
    p.add_argument(
        "--allow-tuning",
        action="store_true",
        help="let Foxglove set the tunable parameters (Parameters panel) and call the operator "
        "services (arm, disarm, switch law); without it the parameters are read-only and only "
        "the mark service is offered; with --allow-remote it needs --tls-cert/--tls-key",
    )
    p.add_argument(
        "--tls-cert",
        metavar="FILE",
        help="PEM certificate (chain): serve wss:// only; every change then needs the access "
        "token, on any host",
    )
    p.add_argument("--tls-key", metavar="FILE", help="PEM private key of --tls-cert (mode 0600)")
    p.add_argument(
        "--print-token",
        action="store_true",
        help="print the access token of the rig key (--key-file) and exit: a client sets the "
        "parameter hil.token to it over wss:// before it may tune",
    )
    p.add_argument(
        "--duration",
        type=duration(zero_means_forever=True),
        default=0.0,
        metavar="S",
        help="0 = until stopped",
    )
    add_key_option(p)
    p.add_argument("--json", action="store_true", help="print counters as JSON at the end")
    p.set_defaults(handler=run)


def _access(args: argparse.Namespace) -> tuple[str, object]:
    """The access mode and the TLS identity (None: plain ws://), or a one-line refusal."""
    from rt_controller.errors import ControllerConfigError
    from rt_controller.monitor.access import TlsIdentity, exposure

    if bool(args.tls_cert) != bool(args.tls_key):
        raise ControllerConfigError("--tls-cert and --tls-key go together (wss:// needs both)")
    mode = exposure(
        args.host,
        allow_remote=args.allow_remote,
        allow_tuning=args.allow_tuning,
        tls=bool(args.tls_cert),
    )
    tls = TlsIdentity.load(args.tls_cert, args.tls_key) if args.tls_cert else None
    return mode, tls


def _check_port(host: str, port: int) -> None:
    """A port another server listens on, refused before the wait for the hub (which would
    otherwise blame a rig not yet up); the server binds it again once the hub is there."""
    import errno
    import socket

    from rt_controller.errors import ControllerConfigError

    if port == 0:
        return
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        # as the server binds (tokio sets it): a client's lingering TIME_WAIT is no refusal
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
            sock.listen(1)
        except OSError as exc:
            hint = (
                "(another monitor or rig's live view?); choose another with --port PORT (0 = any)"
                if exc.errno == errno.EADDRINUSE
                else "(an address of this host? see --host)"
            )
            raise ControllerConfigError(
                f"cannot serve Foxglove WebSocket on {host}:{port}: {exc.strerror or exc} {hint}"
            ) from None


def run(args: argparse.Namespace) -> int:
    from hal.config import load_config
    from hal.secoc import configure_key, rig_key
    from hal.signals import stop_on_signals
    from hal.zenoh_session import DEFAULT_WAIT_S
    from rt_controller.commands.param import Interrupted, hub_endpoint, open_hub_session
    from rt_controller.monitor.access import AccessGate, tuning_token
    from rt_controller.monitor.bridge import MonitorBridge
    from rt_controller.monitor.tuning import TuningFrontEnd

    if args.print_token:
        cfg = configure_key(load_config(args.config), args.key_file, "hil monitor")
        print(tuning_token(rig_key(cfg)))
        return 0
    mode, tls = _access(args)
    _check_port(args.host, args.port)
    cfg = configure_key(load_config(args.config), args.key_file, "hil monitor")
    gate = AccessGate(mode, rig_key(cfg))
    # --duration bounds the wait for the hub too (a 3 s view does not wait 10 s for a rig)
    hub_wait = {"wait_s": min(args.duration, DEFAULT_WAIT_S)} if args.duration else {}
    waiting = f"hil monitor: waiting for the zenoh hub at {hub_endpoint(args, cfg)} (no rig yet)"
    wait_s = hub_wait.get("wait_s", DEFAULT_WAIT_S)
    with stop_on_signals() as stop:
        try:
            with _said_after(HUB_NOTE_S if wait_s >= 2 * HUB_NOTE_S else None, waiting):
                session = open_hub_session(args, cfg, stop, **hub_wait)
        except Interrupted as stopped:  # a signal before the hub came
            print(f"hil monitor: {stopped}", file=sys.stderr)
            return stopped.status
        try:
            tuning = TuningFrontEnd(
                session, rig_key(cfg), allow_tuning=args.allow_tuning, gate=gate
            )
            bridge = MonitorBridge(
                cfg, session, host=args.host, port=args.port, tuning=tuning, tls=tls
            )
            try:
                bridge.start()
                print(f"hil monitor: Foxglove WebSocket on {bridge.url}", file=sys.stderr)
                print(f"hil monitor:   parameters {_mode_line(args, mode)}", file=sys.stderr)
                for topic, schema in bridge.channels().items():
                    print(f"hil monitor:   {topic}  [{schema}]", file=sys.stderr)
                _watch(stop, args.duration or None, bridge)
            finally:
                clean = bridge.close()
                counts = dict(bridge.counts)
                if mode == "token":
                    counts.update({f"access_{k}": v for k, v in gate.counts.items()})
        finally:
            session.close()
    if args.json:
        print(strict_json.dumps({"url": bridge.url, "channels": bridge.channels(), **counts}))
    else:
        print("hil monitor: " + ", ".join(f"{k} {v}" for k, v in counts.items()), file=sys.stderr)
    if not clean:  # a client that never reads holds the server's shutdown (and its exit hook)
        print("hil monitor: a client did not close; exiting without waiting", file=sys.stderr)
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
    return 0


@contextlib.contextmanager
def _said_after(delay_s: float | None, line: str) -> Iterator[None]:
    """Say ``line`` on stderr if the block still runs after ``delay_s`` (None: never)."""
    done, lock = threading.Event(), threading.Lock()

    def say() -> None:
        with lock:
            if not done.is_set():
                print(line, file=sys.stderr, flush=True)

    timer = None if delay_s is None else threading.Timer(delay_s, say)
    if timer is not None:
        timer.daemon = True
        timer.start()
    try:
        yield
    finally:
        with lock:
            done.set()
        if timer is not None:
            timer.cancel()


def _watch(stop: threading.Event, duration_s: float | None, bridge: Any) -> None:
    """Serve until ``stop`` or ``duration_s`` (None: no limit); say once when the rig stops
    sending records (:data:`SILENT_S` without any after some came), and when it sends again."""
    end = None if duration_s is None else time.monotonic() + duration_s
    silent = False
    while True:
        left = None if end is None else end - time.monotonic()
        if left is not None and left <= 0:
            return
        if wait_for_stop(stop, 0.5 if left is None else min(0.5, left)):
            return
        last = bridge.last_record_s
        if last is None:
            continue
        quiet_s = time.monotonic() - last
        if quiet_s >= SILENT_S and not silent:
            print(
                f"hil monitor: the rig went silent: no record for {SILENT_S:g} s (stopped "
                "or paused; still serving, the view resumes when a rig sends again)",
                file=sys.stderr,
                flush=True,
            )
        elif quiet_s < SILENT_S and silent:
            print("hil monitor: the rig sends again (records resumed)", file=sys.stderr)
        silent = quiet_s >= SILENT_S


def _mode_line(args: argparse.Namespace, mode: str) -> str:
    """What a client may change, in words (printed at the start)."""
    if mode == "closed":
        return "read-only (a remote view without TLS)"
    if not args.allow_tuning:
        return "read-only (no --allow-tuning)" + (
            "; the mark needs the access token" if mode == "token" else ""
        )
    if mode == "token":
        return "tunable by a connection that set hil.token (hil monitor --print-token)"
    return "tunable by any client of this host (loopback)"
