"""``hil bench``: performance measurements printed as JSON (never asserted in tests)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

from hal import strict_json
from hal.arguments import MAX_DURATION_S, bounded_float, bounded_int, duration, path_given
from hal.config import LAW_NAMES, PROFILES
from hal.config.ranges import RANGES
from rt_controller.commands.common import add_config_option, add_set_option, config_from_args
from rt_controller.commands.progress import Progress, add_quiet_option

SKIPPABLE_S = bounded_float(0, MAX_DURATION_S, lo_inclusive=True, what="seconds")
"""A duration where 0 skips the measurement."""
CONTROL_RATE = bounded_float(
    *RANGES["rates.control_hz"][:2], lo_inclusive=True, what="a control rate in Hz"
)
"""One rate of ``--rates``: in rates.control_hz's range (the runs' configs would refuse it)."""


def rate_list(text: str) -> tuple[float, ...]:
    """``--rates``: comma-separated control rates, refused while parsing (before any run)."""
    rates = tuple(CONTROL_RATE(r) for r in text.split(",") if r.strip())
    if not rates:
        raise argparse.ArgumentTypeError(f"expected control rates like 50,200, got {text!r}")
    names = [f"{r:g}" for r in rates]  # one log per rate, named so (loop-50.mcap)
    twice = sorted({n for n in names if names.count(n) > 1}, key=float)
    if twice:  # a second run would replace the first's log
        raise argparse.ArgumentTypeError(
            f"{', '.join(twice)} Hz given twice in {text!r}; each rate once"
        )
    return rates


def _two_ticks(seconds: float, rate_hz: float, option: str) -> None:
    """Refuse a lockstep run shorter than two control periods (0 skips it): it would log fewer
    than two cycles, so its speed is NaN (no JSON) or, with none, not measured at all."""
    from rt_controller.errors import ControllerConfigError

    if 0 < seconds < 2 / rate_hz:
        raise ControllerConfigError(
            f"{option} {seconds:g} s is shorter than two control periods at {rate_hz:g} Hz "
            f"({2 / rate_hz:g} s): the lockstep run would time nothing (0 skips it)"
        )


def _files_free(folder: Path, names: list[str]) -> None:
    """Refuse a kept folder where a file the bench will write is a folder or not a file."""
    from rt_controller.errors import OutputPathError

    taken = [n for n in names if (folder / n).exists() and not (folder / n).is_file()]
    if taken:
        raise OutputPathError(
            f"--keep {folder}: the bench writes its runs' files there, but {', '.join(taken)} "
            "already exists as a folder or other non-file (remove it or keep elsewhere)"
        )


def _finish(parser: argparse.ArgumentParser, handler: Callable[[argparse.Namespace], int]) -> None:
    """Every bench prints one JSON object; ``--json`` is accepted for symmetry with the rest."""
    parser.add_argument("--json", action="store_true", help="print one JSON object (always JSON)")
    add_quiet_option(parser)
    parser.set_defaults(handler=_said_on_interrupt(parser.prog, handler))


def _said_on_interrupt(
    prog: str, handler: Callable[[argparse.Namespace], int]
) -> Callable[[argparse.Namespace], int]:
    """``handler``, saying in one line that Ctrl-C, SIGTERM or SIGHUP stopped it before any
    figure was printed (exit status 130, 143 or 129); the signal unwinds the bench, so its
    rigs stop and its temporary folders (MCAP logs, the rig's key) are removed."""
    from rt_controller.commands.interrupts import run_interruptible

    return lambda args: run_interruptible(prog, lambda: handler(args), lambda: "no figures")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="measure solver and loop performance (JSON)")
    bench = p.add_subparsers(dest="bench", metavar="WHAT", required=True)
    s = bench.add_parser("solver", help="C/GMRES update time on the paper scenario closed loop")
    add_config_option(s)
    add_set_option(s)
    s.add_argument(
        "--updates",
        type=bounded_int(2, 10_000_000, what="updates"),  # the first one initialises: 1 times none
        default=2000,
        help="updates per configuration",
    )
    _finish(s, run_solver)
    lp = bench.add_parser(
        "loop",
        help="the whole rig in real time at several control rates (lateness, misses, latency)",
    )
    add_config_option(lp)
    add_set_option(lp)
    lp.add_argument(
        "--rates",
        type=rate_list,
        default="50,200,500,1000",
        help="comma-separated control rates in Hz",
    )
    lp.add_argument(
        "--duration", type=duration(), default=10.0, help="seconds per rate (default 10)"
    )
    lp.add_argument("--law", choices=LAW_NAMES, default="rhc", help="default rhc")
    lp.add_argument(
        "--lockstep-duration",
        type=SKIPPABLE_S,
        default=10.0,
        help="simulated seconds of the lockstep speed run (0 = skip)",
    )
    lp.add_argument(
        "--monitor-port",
        type=bounded_int(0, 65535, what="port"),
        metavar="PORT",
        help="also run `hil monitor` on this port during the real-time runs (connect a "
        "client); 0 = a free port, the same for every run, said on stderr",
    )
    lp.add_argument(
        "--host-probe",
        type=bounded_float(0, 600, lo_inclusive=True, what="seconds"),
        default=5.0,
        metavar="S",
        help="first measure the host's own wake-up lateness for S seconds, as `hil bench host` "
        "(reported as `host`; 0 = skip; default 5)",
    )
    lp.add_argument(
        "--keep",
        type=path_given,
        metavar="DIR",
        help="keep the runs' MCAP logs and configs in DIR, replacing an earlier bench's "
        "files of the same names (default: a temporary folder)",
    )
    lp.add_argument(
        "--profile",
        choices=PROFILES,
        default="dsp",
        help="cia402: every run with the dsp profile, then at once with the cia402 profile, "
        "adding SYNC jitter, SYNC-to-TPDO and torque-to-effect latency (default dsp)",
    )
    _finish(lp, run_loop)
    vp = bench.add_parser(
        "vision",
        help="the image pipeline: render and detection time at 640x480 and 1280x1024, error "
        "against eq. (6) with and without noise, frames lost to motion blur at peak speed, "
        "capture-to-publish latency over zenoh",
    )
    add_config_option(vp)
    add_set_option(vp)
    vp.add_argument(
        "--grid",
        type=bounded_int(2, 50, what="poses per axis"),
        default=7,
        help="poses per joint axis of the pose grid (default 7: 49 poses)",
    )
    vp.add_argument(
        "--latency-frames",
        type=bounded_int(0, 100_000, what="frames"),
        default=300,
        help="frames sent at 60 fps through a loopback zenoh hub (0 = skip)",
    )
    vp.add_argument(
        "--lockstep-duration",
        type=SKIPPABLE_S,
        default=5.0,
        metavar="S",
        help="simulated seconds of the lockstep rigs: images, images of a clean camera, "
        "images with no image log, analytic (0 = skip)",
    )
    vp.add_argument(
        "--realtime-duration",
        type=SKIPPABLE_S,
        default=10.0,
        metavar="S",
        help="seconds of a realtime rig with images at 60 fps, timing the pipeline per frame "
        "while it runs (0 = skip)",
    )
    _finish(vp, run_vision)
    hp = bench.add_parser(
        "host",
        help="how late this host wakes a SCHED_FIFO 99 thread on each CPU (cyclictest's "
        "measurement; the floor under the loop's lateness), and the hypervisor's steal",
    )
    hp.add_argument("--duration", type=duration(), default=10.0, help="seconds (default 10)")
    hp.add_argument(
        "--period-us",
        type=bounded_int(50, 1_000_000, what="--period-us"),
        default=1000,
        help="release period of each probe in microseconds (default 1000)",
    )
    _finish(hp, run_host)
    sw = bench.add_parser(
        "sweep",
        help="hil sweep's runs/s: serial, on 1 worker and on all workers (scaling, efficiency)",
    )
    sw.add_argument(
        "--runs",
        type=bounded_int(1, 100_000, what="--runs"),
        default=40,
        help="simulate runs per measurement (default 40)",
    )
    sw.add_argument("--duration", type=duration(), default=6.0, help="simulated s per run")
    sw.add_argument("--law", choices=LAW_NAMES, default="rhc", help="default rhc")
    sw.add_argument(
        "--workers",
        type=bounded_int(1, 256, what="--workers"),
        help="the 'all workers' count (default: one per CPU)",
    )
    sw.add_argument(
        "--rig-runs",
        type=bounded_int(0, 1000, what="--rig-runs"),
        default=4,
        help="rig engine runs per measurement (0 = skip the rig; default 4)",
    )
    sw.add_argument("--rig-duration", type=duration(), default=2.0, help="simulated s per rig run")
    _finish(sw, run_sweep)
    sk = bench.add_parser(
        "soak",
        help="the realtime rig for a long run: RSS of each process over time, its growth "
        "after the warm-up, deadline misses, the log's size, the recorder's backlog",
    )
    add_config_option(sk)
    add_set_option(sk)
    sk.add_argument(
        "--duration", type=duration(), default=1800.0, help="seconds of run (default 1800)"
    )
    sk.add_argument(
        "--sample", type=duration(), default=10.0, help="seconds between samples (default 10)"
    )
    sk.add_argument(
        "--warmup",
        type=SKIPPABLE_S,
        default=60.0,
        metavar="S",
        help="RSS growth is measured from the first sample after S seconds (default 60)",
    )
    sk.add_argument("--law", choices=LAW_NAMES, default="rhc", help="default rhc")
    sk.add_argument(
        "--keep",
        type=path_given,
        metavar="DIR",
        help="keep the run's MCAP log and config in DIR, replacing an earlier bench's "
        "(default: drop)",
    )
    _finish(sk, run_soak)
    tp = bench.add_parser(
        "tuning",
        help="in a realtime run: request-to-effect latency of hil param sets (ms, periods) "
        "and the decide-phase cost of a law switch rhc -> ioc -> rhc",
    )
    tp.add_argument(
        "--requests",
        type=bounded_int(1, 10_000, what="--requests"),
        default=50,
        help="parameter sets to time (default 50)",
    )
    tp.add_argument(
        "--workdir",
        type=path_given,
        metavar="DIR",
        help="keep the run's MCAP log (tuning.mcap) and key (bench.key) in DIR, replacing an "
        "earlier bench's (default: a temporary folder, removed)",
    )
    _finish(tp, run_tuning)


def run_solver(args: argparse.Namespace) -> int:
    from rt_controller.rig.bench_solver import bench_solver

    cfg = config_from_args(args)
    progress = Progress.of(args, "hil bench solver")
    with progress.stage(
        f"timing {args.updates} C/GMRES updates at N = {cfg.rhc.steps}, then the sweep over N "
        "(numba compiles the solver on a cold cache)"
    ):
        result = bench_solver(cfg, updates=args.updates)
    print(strict_json.dumps(result))
    return 0


def run_vision(args: argparse.Namespace) -> int:
    from rt_controller.commands.vision import emulated_camera
    from rt_controller.rig.bench_vision import bench_vision

    cfg = config_from_args(args)
    _two_ticks(args.lockstep_duration, cfg.rates.control_hz, "--lockstep-duration")
    render, truth = emulated_camera()
    progress = Progress.of(args, "hil bench vision")
    out = bench_vision(
        cfg,
        render,
        truth,
        grid=args.grid,
        latency_frames=args.latency_frames,
        lockstep_s=args.lockstep_duration,
        realtime_s=args.realtime_duration,
        progress=progress.line,
    )
    print(strict_json.dumps(out))
    rt = out.get("realtime") or {"problems": [], "exit_codes": {}}
    failed = [f"{n} exited {c}" for n, c in rt["exit_codes"].items() if c]
    if rt["problems"] or failed:  # the figures are printed either way; the status tells the truth
        why = "; ".join([*rt["problems"], *failed])
        print(f"hil bench vision: realtime run not clean: {why}", file=sys.stderr)
        return 1
    return 0


def run_sweep(args: argparse.Namespace) -> int:
    from rt_controller.extras import require_extra

    require_extra("sweep", "this command")
    from rt_controller.commands.sweep import simulate_plant
    from rt_controller.sweep.bench import bench_sweep

    progress = Progress.of(args, "hil bench sweep")
    with progress.stage("timing the sweep engines serially, on 1 worker and on all workers"):
        result = bench_sweep(
            simulate_plant(),
            runs=args.runs,
            duration_s=args.duration,
            law=args.law,
            workers=args.workers,
            rig_runs=args.rig_runs,
            rig_duration_s=args.rig_duration,
        )
    print(strict_json.dumps(result))
    failed = [e for e in result["engines"] if e["failed"]]
    for e in failed:  # runs/s of failed runs are not the engine's speed: the status says so
        print(
            f"hil bench sweep: {e['failed']} {e['engine']} runs failed: {'; '.join(e['errors'])}",
            file=sys.stderr,
        )
    return 1 if failed else 0


def run_soak(args: argparse.Namespace) -> int:
    from rt_controller.commands.output import output_dir
    from rt_controller.errors import ControllerConfigError
    from rt_controller.rig.bench_soak import bench_soak

    if args.warmup >= args.duration:  # growth needs samples after the warm-up
        raise ControllerConfigError(
            f"--warmup must be less than --duration ({args.duration:g} s), got {args.warmup:g}"
        )
    if args.warmup + 2 * args.sample > args.duration:  # else no RSS growth, or no RSS at all
        raise ControllerConfigError(
            f"--sample {args.sample:g} s leaves fewer than two RSS samples after the --warmup "
            f"({args.warmup:g} s) in --duration {args.duration:g} s: need warmup + 2 x sample "
            "<= duration"
        )
    cfg = config_from_args(args)
    keep = output_dir(args.keep, "--keep") if args.keep is not None else None
    progress = Progress.of(args, "hil bench soak")
    with progress.stage(
        f"running the realtime rig with {args.law} for {args.duration:g} s, sampling every "
        f"{args.sample:g} s"
    ):
        result = bench_soak(
            cfg,
            duration=args.duration,
            sample_s=args.sample,
            warmup_s=args.warmup,
            law=args.law,
            keep=keep,
        )
    print(strict_json.dumps(result))
    if result["problems"]:  # the figures are printed either way; the exit status tells the truth
        print(f"hil bench soak: run not clean: {'; '.join(result['problems'])}", file=sys.stderr)
    return 1 if result["problems"] else 0


def run_tuning(args: argparse.Namespace) -> int:
    from rt_controller.commands.output import output_dir
    from rt_controller.rig.bench_tuning import bench_tuning
    from rt_controller.rig.failures import with_tail

    # a bad path before the rig starts
    workdir = output_dir(args.workdir, "--workdir") if args.workdir is not None else None
    progress = Progress.of(args, "hil bench tuning")
    with progress.stage(f"a realtime run with {args.requests} parameter sets"):
        result = bench_tuning(workdir, requests=args.requests)
    print(strict_json.dumps(result))
    if result["rig_exit"] != 0:  # the figures are printed either way; the status tells the truth
        log = f" (its log: {result['log']})" if result["log"] else ""
        line = f"hil bench tuning: the rig exited with status {result['rig_exit']}{log}"
        print(with_tail(line, result.get("stderr_tail", "")), file=sys.stderr)
    return 0 if result["rig_exit"] == 0 else 1


def run_host(args: argparse.Namespace) -> int:
    from rt_controller.rig.bench_host import bench_host

    progress = Progress.of(args, "hil bench host")
    with progress.stage(f"measuring this host's wake-up lateness for {args.duration:g} s"):
        result = bench_host(args.duration, args.period_us)
    print(strict_json.dumps(result))
    return 0


def run_loop(args: argparse.Namespace) -> int:
    from rt_controller.commands.output import output_dir
    from rt_controller.rig.bench_loop import bench_files, bench_loop

    rates = args.rates  # a tuple, each in range (rate_list)
    cfg = config_from_args(args)
    _two_ticks(args.lockstep_duration, cfg.rates.control_hz, "--lockstep-duration")
    keep = output_dir(args.keep, "--keep") if args.keep is not None else None
    if keep is not None:  # a later run's file taken by a folder would lose the earlier figures
        _files_free(keep, bench_files(rates, args.lockstep_duration > 0, args.profile))
    measured = args.host_probe + len(rates) * args.duration + args.lockstep_duration
    progress = Progress.of(args, "hil bench loop")
    monitor_port = args.monitor_port
    if monitor_port == 0:  # any port: one for every run, said, or no client could connect
        from hal.zenoh_session import free_loopback_port

        monitor_port = free_loopback_port()
        print(
            f"hil bench loop: live view of each real-time run on ws://127.0.0.1:{monitor_port} "
            "(--monitor-port 0)",
            file=sys.stderr,
        )
    with progress.stage(
        f"running the rig with {args.law} at {', '.join(f'{r:g}' for r in rates)} Hz, "
        f"{args.duration:g} s each (about {measured:.0f} s of measurement, plus start-ups)"
    ):
        result = bench_loop(
            cfg,
            rates=rates,
            duration=args.duration,
            law=args.law,
            lockstep_duration=args.lockstep_duration,
            monitor_port=monitor_port,
            keep=keep,
            host_probe_s=args.host_probe,
            profile=args.profile,
        )
    print(strict_json.dumps(result))
    runs = result["rates"] + result.get("dsp_rates", [])
    unclean = [r for r in runs if r["problems"]]
    for r in unclean:  # the figures are printed either way; the exit status tells the truth
        print(
            f"hil bench loop: {r.get('profile', 'dsp')} run not clean at {r['rate_hz']:g} Hz: "
            f"{'; '.join(r['problems'])}",
            file=sys.stderr,
        )
    return 1 if unclean else 0
