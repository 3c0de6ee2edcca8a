"""``hil emulator``: the emulated DSP of the arm on a CAN bus, camera poses on zenoh.

The ``hil`` CLI (:mod:`rt_controller.commands.emulator`) only registers the options with
:func:`add_emulator_arguments` and dispatches to :func:`run_emulator`; everything else lives here.

Behaviour:

* opens the bus with :func:`hal.bus.open_bus` (``--can``, default ``transport.can`` of the config:
  ``auto`` = python-can's configuration, else ``socketcan:vcan0`` if it exists, else host-local
  ``udp_multicast``) and runs the emulated DSP (:mod:`plant_emulator.dsp_node`) with the runner
  of its clock mode (:func:`plant_emulator.dsp.make_dsp`: realtime or lockstep);
* unless ``--no-vision-link``, it is the zenoh hub of the rig (router listening on
  ``--zenoh-endpoint``, or a ``--zenoh-config`` file) and publishes the camera pose on
  ``hil/emulator/camera_pose`` for the vision process (:mod:`plant_emulator.pose_link`), and
  takes the harness's commands from ``hil/sim/control`` (:mod:`hal.sim_control`: a lockstep
  DSP restarts the scenario with the named camera noise seed; rejected messages are counted in
  the summary's ``sim_control``);
* with ``camera.model = "image"`` (unless ``--no-camera``) it is also the rig's camera: a thread
  renders frames from those poses and streams them on ``hil/camera/frame``
  (:mod:`plant_emulator.camera_node`); in lockstep it then waits for a frame grabber (or a pose
  subscriber: the analytic vision process) before period 0;
* prints one line on stderr saying where it serves, e.g.
  ``hil emulator: serving the arm on socketcan:vcan0 (realtime)``;
* SIGTERM / SIGINT (or ``--duration``): torque off, a final DspStatus, bus and session closed,
  exit status 0; ``--json`` prints the final counters as one JSON object on stdout.

An unavailable transport raises :class:`~hal.errors.HalTransportError` (one line saying what to
do), which the ``hil`` CLI turns into exit status 2.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Any

from hal import strict_json
from hal.arguments import MAX_DURATION_S, add_key_option, bounded_float, duration
from hal.config.hardware import PROFILES

if TYPE_CHECKING:  # heavy imports stay out of `hil --help`
    from plant_emulator.pose_link import PoseLink

DEFAULT_VISION_WAIT_S = 10.0
"""Lockstep: how long to wait for the vision process to subscribe before period 0."""


def add_emulator_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hil emulator``."""
    p.add_argument(
        "--can",
        metavar="INTERFACE[:CHANNEL]",
        help="CAN bus, e.g. socketcan:vcan0, udp_multicast, virtual (default: transport.can of "
        "the config, 'auto' = python-can config, else socketcan:vcan0 if present, else "
        "host-local udp_multicast)",
    )
    p.add_argument("--config", metavar="FILE", help="rig configuration (TOML); default: embedded")
    add_key_option(p)
    p.add_argument(
        "--profile",
        choices=PROFILES,
        help="the hardware to emulate: dsp (our DSP, hal/hil.dbc with SecOC) or cia402 (two "
        "CANopen CiA 402 drives in cyclic synchronous torque mode, node ids from [cia402], paced "
        "by the controller's SYNC); default: hardware.profile of the config (dsp)",
    )
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="lockstep clock: send Sync once per control period and advance the physics only "
        "after the controller's command for it (default: controller.clock of the config)",
    )
    p.add_argument(
        "--duration",
        type=duration(zero_means_forever=True),
        default=0.0,
        metavar="S",
        help="stop after S seconds (simulated seconds in lockstep); 0 = until SIGTERM/SIGINT",
    )
    p.add_argument(
        "--state-rate",
        type=bounded_float(0.0, 100_000.0, what="state rate in Hz"),
        metavar="HZ",
        help="joint-state frame rate on the DSP's own clock (rates.state_hz with "
        "dsp.state_sync = free; at most rates.physics_hz); default: one per control period, "
        "in step with the controller's commands",
    )
    p.add_argument("--json", action="store_true", help="print the final counters as one JSON line")
    p.add_argument(
        "--zenoh-endpoint",
        metavar="tcp/127.0.0.1:PORT",
        help="loopback endpoint the emulator listens on as the rig's zenoh hub "
        "(default: transport.zenoh_endpoint, tcp/127.0.0.1:7447)",
    )
    p.add_argument(
        "--zenoh-config",
        metavar="FILE",
        help="zenoh json5 config replacing the loopback defaults (multi-host setups)",
    )
    p.add_argument(
        "--no-vision-link",
        dest="vision_link",
        action="store_false",
        help="do not open zenoh / publish camera poses (CAN only)",
    )
    p.add_argument(
        "--no-camera",
        dest="camera",
        action="store_false",
        help="with camera.model = image: do not render and stream camera frames (another "
        "camera serves hil/camera/frame)",
    )
    p.add_argument(
        "--vision-wait",
        type=bounded_float(0, MAX_DURATION_S, lo_inclusive=True, what="seconds"),
        default=DEFAULT_VISION_WAIT_S,
        metavar="S",
        help="lockstep: wait up to S seconds for the vision process before period 0 (default 10)",
    )


def _config(args: argparse.Namespace) -> Any:
    from hal.config import load_config
    from hal.errors import HalConfigError

    cfg = load_config(args.config)
    if args.state_rate is not None:
        try:
            cfg = cfg.with_overrides({"rates.state_hz": args.state_rate, "dsp.state_sync": "free"})
        except HalConfigError as exc:
            raise HalConfigError(f"--state-rate: {exc}") from exc
    from hal.secoc import configure_key

    cfg = configure_key(cfg, args.key_file, "hil emulator")
    return cfg


def fifo_priority(priority: int) -> str | None:
    """SCHED_FIFO at ``priority`` for the calling thread (the DSP loop; zenoh's threads keep
    normal scheduling); 0 leaves scheduling alone. A refusal (no CAP_SYS_NICE) is returned as
    a one-line warning, never raised: the emulator then runs with normal scheduling."""
    from hal.fifo import fifo_thread

    why = fifo_thread(priority)
    return None if why is None else f"{why}; the DSP loop runs with normal scheduling"


def run_emulator(args: argparse.Namespace) -> int:
    """Body of ``hil emulator``; returns the exit status (HalError propagates to the CLI)."""
    from hal.lean_start import without_scipy_linalg
    from hal.signals import stop_on_signals

    without_scipy_linalg()  # before numba: it would import SciPy's BLAS, which no kernel uses

    with stop_on_signals() as stop:  # before the slow imports
        return _serve(args, stop)


def _profile(args: argparse.Namespace) -> str:
    """``--profile``, else ``hardware.profile`` of the configuration (``hil up`` passes it so)."""
    if args.profile is not None:
        return args.profile
    from hal.config import load_config

    return load_config(args.config).hardware.profile


def _serve(args: argparse.Namespace, stop: threading.Event) -> int:
    from hal.arguments import check_zenoh_options
    from hal.bus import open_bus, process_spec
    from plant_emulator.dsp import make_dsp

    check_zenoh_options(args)
    if _profile(args) == "cia402":
        from plant_emulator.cia402.entry import serve_cia402

        if args.state_rate is not None:  # the drives answer each SYNC: no free-running state
            from hal.errors import HalConfigError

            raise HalConfigError(
                "--state-rate: only for the dsp profile (CiA 402 drives send their state per "
                "SYNC); drop --state-rate or use --profile dsp"
            )

        return serve_cia402(args, stop)
    cfg = _config(args)
    lockstep = bool(args.lockstep) or cfg.controller.clock == "lockstep"
    spec = args.can or cfg.transport.can
    where = str(process_spec(spec))  # HalConfigError: malformed, or in-process only
    mode = "lockstep" if lockstep else "realtime"
    with contextlib.ExitStack() as stack:
        bus = stack.enter_context(open_bus(spec))
        link: PoseLink | None = None
        listening: Callable[[], bool] | None = None
        """Whether the process lockstep waits for before period 0 is there."""
        zenoh_where = ""
        session = None
        if args.vision_link:
            from hal.secoc import rig_key
            from hal.zenoh_session import open_session
            from plant_emulator.pose_link import PoseLink, PosePublisher, wait_until

            session = stack.enter_context(
                open_session(
                    cfg,
                    listen=True,
                    endpoint=args.zenoh_endpoint,
                    config_file=args.zenoh_config,
                )
            )
            publisher = PosePublisher(session, key=rig_key(cfg))
            stack.callback(publisher.close)
            link = PoseLink(publisher)
            listening = publisher.has_subscribers
            zenoh_where = f", camera poses on zenoh {zenoh_where_of(session)}"
            if args.camera and cfg.camera.model == "image" and not stop.is_set():
                from plant_emulator.camera_link import start_camera  # compiles the renderer

                link.camera, frames = start_camera(cfg, session, stack, rig_key(cfg))
                poses_seen = publisher.has_subscribers
                listening = lambda: frames.has_subscribers() or poses_seen()  # noqa: E731
                c = cfg.camera
                zenoh_where += f", camera frames {c.width_px}x{c.height_px}"
        node = make_dsp(
            cfg,
            bus,
            lockstep=lockstep,
            pose_sink=link,
            on_reset=None if link is None else link.new_run,
            on_fault=_say_fault,
        )
        sim_control = None
        if session is not None:
            sim_control = stack.enter_context(serve_sim_control(session, node, rig_key(cfg)))
        if not stop.is_set():  # stopped during start-up: compile nothing more (seconds, cold)
            node.warm_up()
        print(
            f"hil emulator: serving the arm on {where} ({mode}){zenoh_where}",
            file=sys.stderr,
            flush=True,
        )
        if (
            lockstep
            and link is not None
            and args.vision_wait > 0
            and listening is not None
            and not wait_until(listening, args.vision_wait, stop)
            and not stop.is_set()
        ):
            print(
                f"hil emulator: no vision process subscribed within {args.vision_wait:g} s; "
                "starting without it",
                file=sys.stderr,
                flush=True,
            )
        if not lockstep:
            warning = fifo_priority(cfg.dsp.rt_priority)
            if warning:
                print(f"hil emulator: warning: {warning}", file=sys.stderr, flush=True)
        t0 = time.monotonic()
        stats = node.run(stop, args.duration)
        wall_s = time.monotonic() - t0
        summary: dict[str, Any] = {
            "transport": where,
            "mode": mode,
            "sim_time_s": node.world.t,
            "wall_time_s": wall_s,
            "q": [float(v) for v in node.world.q],
            "dq": [float(v) for v in node.world.dq],
            "watchdog_period_ms": node.watchdog_ns * 1e-6,
            "poses_published": 0 if link is None else link.publisher.published,
            "pose_errors": 0 if link is None else link.errors,
            "camera": None if link is None or link.camera is None else link.camera.stats.as_dict(),
            "sim_control": None if sim_control is None else sim_control.counts.as_dict(),
            **stats.as_dict(),
        }
        summary = with_callback_errors(summary, session)  # the session still open
    if args.json:
        print(strict_json.dumps(summary), flush=True)
    else:
        print(
            f"hil emulator: {summary['sim_time_s']:.3f} s simulated in {wall_s:.3f} s, "
            f"{stats.commands} commands, {stats.state_frames} states, "
            f"{stats.watchdog_trips} watchdog trips, "
            f"{stats.rejected.get('rejected', 0)} frames rejected"
            f"{callback_errors_text(summary)}",
            flush=True,
        )
    return 0


def with_callback_errors(summary: dict[str, Any], session: Any) -> dict[str, Any]:
    """``summary`` plus ``callback_errors``: the zenoh session's messages lost to an exception
    in a callback (the camera's region requests, the harness's sim control), which the
    session swallows: a bug if not zero, then also a warning line on stderr. None without a
    session (``--no-vision-link``)."""
    n = None if session is None else int(session.callback_errors)
    if n:
        print(
            f"hil emulator: warning: {n} zenoh message(s) lost to errors in callbacks (a bug)",
            file=sys.stderr,
            flush=True,
        )
    return {**summary, "callback_errors": n}


def callback_errors_text(summary: dict[str, Any]) -> str:
    """The text summary's part for ``callback_errors`` (empty without a session)."""
    n = summary.get("callback_errors")
    return "" if n is None else f", {n} zenoh callback errors"


def zenoh_where_of(session: Any) -> str:
    """Where the banner says the zenoh session is: its loopback endpoint, or for a
    ``--zenoh-config`` file the endpoints that file makes it listen on (connect to, if none),
    e.g. ``tcp/127.0.0.1:7447 (listen endpoints of hub.json5)``: the file's name alone does not
    tell a user where to point the other processes."""
    if session.source == "loopback":
        return str(session.endpoint)
    import zenoh

    zcfg = zenoh.Config.from_file(session.source)  # opened already: it parses
    for role in ("listen", "connect"):
        found = json.loads(zcfg.get_json(f"{role}/endpoints") or "[]")
        if isinstance(found, dict):  # per mode: {"router": [...], "peer": [...]}
            found = found.get(session.mode) or []
        if found:
            return f"{', '.join(map(str, found))} ({role} endpoints of {session.source})"
    return f"no endpoints of {session.source}"


@contextlib.contextmanager
def serve_sim_control(session: Any, node: Any, key: bytes) -> Iterator[Any]:
    """Take the harness's commands on ``hil/sim/control`` (:mod:`hal.sim_control`) for
    ``node`` (a scenario reset with its camera noise seed,
    :meth:`~plant_emulator.dsp_lockstep.LockstepDsp.request_reset`) while the context is open;
    yields the receiver, whose ``counts`` say what was rejected."""
    from hal.sim_control import KEY_SIM_CONTROL, SimControlReceiver

    receiver = SimControlReceiver(lambda msg: node.request_reset(msg.seed), key=key)
    subscriber = session.subscribe(KEY_SIM_CONTROL, receiver.feed)
    try:
        yield receiver
    finally:
        subscriber.undeclare()


def _say_fault(line: str) -> None:
    """A fault of the drive, on stderr the moment it happens (``hil up`` waits for a watchdog
    trip's line after the controller died)."""
    print(f"hil emulator: fault: {line}", file=sys.stderr, flush=True)


def main(argv: Sequence[str] | None = None) -> int:
    """Stand-alone entry point (``python -m plant_emulator.entry``), same as ``hil emulator``."""
    from hal.signals import run_standalone

    parser = argparse.ArgumentParser(
        prog="hil emulator", description="Emulated DSP of the two-link arm on CAN."
    )
    add_emulator_arguments(parser)
    args = parser.parse_args(argv)
    return run_standalone("hil emulator", lambda: run_emulator(args))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
