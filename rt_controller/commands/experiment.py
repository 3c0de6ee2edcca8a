"""``hil experiment``: the paper's Fig. 3, Fig. 4 and Table I, run through the real daemons."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hal import strict_json
from hal.arguments import bounded_float, bounded_int, duration, path_given
from rt_controller.commands.common import add_profile_option, add_set_option
from rt_controller.commands.progress import add_quiet_option
from rt_controller.config_rules import parse_sets

if TYPE_CHECKING:
    from rich.console import Console

    from rt_controller.commands.progress import Progress
    from rt_controller.rig.experiment import Settings
    from rt_controller.sweep.executor import Cluster

DESCRIPTION = """\
Reproduces the paper's experiments (Section V) on the emulated rig: `hil emulator`,
`hil vision` and `hil controller` run as separate processes (lockstep by default, --realtime for
real-time runs) and every run logs to MCAP. Lockstep runs that share the emulator's and vision's
configuration (all but the controller's sections) run on one set of processes: the controller
resets the emulated DSP's scenario between them (on the simulator-control channel, zenoh
hil/sim/control), which starts each run exactly as fresh processes would. --fresh-processes
starts the rig anew for every run. --profile (hardware.profile) picks the hardware behind the
controller's seam: dsp (the default) or cia402 (CANopen CiA 402 drives; its runs always start
the rig anew, the scenario reset being the emulated DSP's); report.md and results.json name it.

  fig3    RHC (T = 0.02 s) vs inverse-optimal vs passivity-based control: f, xi, u over time
          (solid RHC, dashed IOC, dash-dot PBC) and J of each law
  fig4    RHC with T = 0.02, 0.1, 1.0 s: f, xi, u over time and J of each horizon
  table1  J of each horizon, --reps runs each, per-run values (sorted ascending per row, like
          the paper's Table I) and the average
  all     the three (a run shared by fig3 and fig4 runs once)

When only the horizon T is set, N = max(rhc.steps, ceil(T / 0.05 s)) steps (T = 1.0 s -> 20),
as with `hil controller --horizon T`. Repetitions of table1 differ by the camera noise seed
(repetition i uses seed i). The default camera renders images: the seed draws its sensor's
noise, and --noise (camera.noise_px, the analytic camera's pixel noise) is refused. With
camera.model = analytic, table1 uses --noise, else camera.noise_px of the config, else 0.5 px
(with no noise every lockstep repetition would be identical); fig3 and fig4 use --noise, else
the config's (0 by default). --set KEY=VALUE changes a key for every run (e.g.
--set camera.model=analytic); the keys the experiment sets per run (controller.law,
rhc.horizon, camera.noise_px, controller.clock, hardware.profile, transport.*) are refused,
naming what sets them.

The output folder (default experiments/<timestamp>/) gets logs/*.mcap, configs/*.toml (each
run's full configuration), PNG figures, report.md (what was run, J tables, figures, the paper's
Table I for comparison, and per run the command that repeats it, run inside the output folder:
`hil --target-of LOG up --config CONFIG --log NAME.rerun.mcap --force`, on the CPU target its
log records) and results.json (also printed by --json).
A failed run is reported with the error of its process; the experiment then exits with status 1
after the remaining runs (it gives up after three failures in a row). A failed run's J enters
no average or claim: a Table I average over fewer runs says so, e.g. "24.011 (4 of 5)". A
--can bus that cannot be opened is refused before any run.

The runs go as Dask tasks (one per set of processes) on the executor of `hil sweep`: a local
cluster of --jobs workers by default, or an existing cluster with --scheduler, whose workers
must have this package installed and see the --out folder at the same path; the batch of a
worker that dies is run again on another. Lockstep runs on private buses (the default
host-local bus) run --jobs at a time (or one per worker of the --scheduler cluster), one per
CPU by default: each lockstep run is deterministic, so the results are the same as one at a
time. Real-time runs, and runs on one shared bus (--can, SocketCAN), run one at a time.
"""

DEFAULT_REPS = 5


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "experiment",
        help="reproduce the paper's Fig. 3, Fig. 4 and Table I on the rig (report.md, PNGs)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("which", choices=("fig3", "fig4", "table1", "all"), help="what to run")
    p.add_argument(
        "--out",
        type=path_given,
        metavar="DIR",
        help="output folder (default experiments/<timestamp>); one that holds an experiment "
        "already is refused unless --force",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="run into an --out that holds an experiment: its results.json, report.md, "
        "figures and the logs of the runs planned anew are removed before the first run",
    )
    p.add_argument(
        "--reps",
        type=bounded_int(1, 1000, what="repetitions"),
        metavar="N",
        help=f"table1 runs per horizon ({DEFAULT_REPS}); refused for fig3 and fig4",
    )
    p.add_argument(
        "--duration", type=duration(), default=10.0, metavar="S", help="plant time per run (10)"
    )
    p.add_argument(
        "--noise",
        type=bounded_float(0.0, 1000.0, lo_inclusive=True, what="pixel noise"),
        metavar="PX",
        help="camera.model = analytic: pixel noise std for every run (default: the config's; "
        "table1: 0.5 px if the config's is 0); refused with the rendering camera",
    )
    p.add_argument("--realtime", action="store_true", help="real-time runs instead of lockstep")
    p.add_argument("--config", metavar="FILE", help="rig configuration (TOML); default: embedded")
    add_set_option(p)
    add_profile_option(p)
    p.add_argument(
        "--can",
        metavar="INTERFACE[:CHANNEL]",
        help="CAN bus (default: the config's; the automatic host-local udp_multicast bus gets a "
        "private port per run so other rigs on the host cannot interfere)",
    )
    p.add_argument(
        "--jobs",
        type=bounded_int(1, 16, what="jobs"),
        metavar="N",
        help="rigs run at once, the workers of the local Dask cluster (default: one per CPU "
        "for lockstep runs on private buses, else 1; lockstep results do not depend on it)",
    )
    p.add_argument(
        "--scheduler",
        metavar="tcp://HOST:8786",
        help="run on this existing Dask cluster instead of a local one (its workers need this "
        "package installed and the --out folder at the same path)",
    )
    p.add_argument(
        "--fresh-processes",
        action="store_true",
        help="start the rig anew for every lockstep run instead of resetting the emulated "
        "scenario between runs on one set of processes (slower, same results)",
    )
    p.add_argument("--json", action="store_true", help="print results.json on stdout")
    add_quiet_option(p)  # a failed run is still said, after the runs
    p.set_defaults(handler=run)


def default_out(root: Path = Path("experiments")) -> Path:
    """``experiments/<YYYYmmdd-HHMMSS>``, with a suffix if that exists already."""
    base = root / time.strftime("%Y%m%d-%H%M%S")
    out, i = base, 1
    while out.exists():
        i += 1
        out = base.with_name(f"{base.name}-{i}")
    return out


def command_line(args: argparse.Namespace, out: Path) -> str:
    """The canonical command line of this experiment (for report.md)."""
    parts = ["hil", "experiment", args.which, "--out", str(out)]
    if args.which in ("table1", "all"):
        parts += ["--reps", str(args.reps or DEFAULT_REPS)]
    parts += ["--duration", f"{args.duration:g}"]
    if args.noise is not None:
        parts += ["--noise", f"{args.noise:g}"]
    if args.realtime:
        parts.append("--realtime")
    if args.config:
        parts += ["--config", args.config]
    for key, value in parse_sets(args.sets).items():
        parts += ["--set", f"{key}={json.dumps(value)}"]
    if args.profile:
        parts += ["--profile", args.profile]
    if args.can:
        parts += ["--can", args.can]
    if args.jobs is not None:
        parts += ["--jobs", str(args.jobs)]
    if args.scheduler:
        parts += ["--scheduler", args.scheduler]
    if args.fresh_processes:
        parts.append("--fresh-processes")
    return shlex.join(parts)


def run(args: argparse.Namespace) -> int:
    """Body of ``hil experiment``: every option is checked (the config, each run's
    configuration, the ``--scheduler`` reached) before the output folder is made, so a bad
    one leaves nothing behind."""
    from rich.console import Console

    from rt_controller.extras import require_extra

    require_extra("sweep", "this command")  # the runs go as tasks on the sweep's Dask executor

    from rt_controller.commands.progress import Progress
    from rt_controller.rig.supervise import signals_deferred
    from rt_controller.sweep.executor import open_cluster

    out = Path(args.out) if args.out else default_out()
    if args.scheduler:  # the workers read and write the runs' files by these paths
        out = out.absolute()
    if not args.force:
        unused(out)
    settings = settings_from_args(args, out)
    err = Console(stderr=True, quiet=args.quiet)  # the runs' lines and the progress bar
    progress = Progress("hil experiment", quiet=args.quiet, console=err)
    local = settings.scheduler is None
    where = "starting the local Dask cluster" if local else f"connecting to {settings.scheduler}"
    with progress.stage(where):
        cl = open_cluster(
            settings.effective_jobs() if local else None,
            settings.scheduler,
            processes=False,
            workers_option="--jobs",
        )
    try:
        return run_on(cl, args, settings, err, progress)
    finally:  # a stop signal now (an impatient second Ctrl-C) asks for nothing more
        with signals_deferred(deliver=False):
            cl.close()


SET_BY_OPTION = {
    "controller.law": "each experiment sets the law of its runs",
    "rhc.horizon": "each experiment sets the horizon of its runs",
    "camera.noise_px": "use --noise",
    "controller.clock": "lockstep, or --realtime",
    "hardware.profile": "use --profile",
    "transport": "the runs' transports come from --can and the --config file",
}
"""Keys (or sections) ``--set`` refuses, and what sets them instead."""


EXPERIMENT_FILES = ("results.json", "report.md", "logs", "configs")
"""What an experiment leaves in its folder: any of them there, and it holds one already."""


def unused(out: Path) -> None:
    """Refuse an ``--out`` that holds an experiment: its runs' logs would be replaced."""
    from rt_controller.errors import ControllerConfigError

    there = [name for name in EXPERIMENT_FILES if (out / name).exists()]
    if there:
        raise ControllerConfigError(
            f"--out {out}: holds an experiment already ({', '.join(there)}); its logs would "
            "be replaced (pass --force to run into it)"
        )


def settings_from_args(args: argparse.Namespace, out: Path) -> Settings:
    """The experiment's settings, validated with every run's configuration (a config file that
    does not load, a ``--noise`` the camera cannot apply): nothing is written yet."""
    from rt_controller.control.simulate import tick_count, too_short
    from rt_controller.errors import ControllerConfigError
    from rt_controller.rig.experiment import EXPERIMENTS, Settings, plan, run_config

    settings = Settings(
        experiments=EXPERIMENTS if args.which == "all" else (args.which,),
        out=out,
        reps=args.reps or DEFAULT_REPS,
        duration_s=args.duration,
        noise_px=args.noise,
        realtime=args.realtime,
        config=args.config,
        can=args.can,
        jobs=args.jobs,
        scheduler=args.scheduler,
        fresh_processes=args.fresh_processes,
        profile=args.profile,
        sets=parse_sets(args.sets),
    )
    for key in settings.sets:
        if (why := SET_BY_OPTION.get(key) or SET_BY_OPTION.get(key.partition(".")[0])) is not None:
            raise ControllerConfigError(f"--set {key}: {why}")
    settings.validate()
    if args.reps is not None and args.which in ("fig3", "fig4"):  # one run per law / horizon
        raise ControllerConfigError(f"--reps: {args.which} has no repetitions (table1 has)")
    for specs in plan(settings, settings.base_config()).values():
        for spec in specs:
            rate = run_config(settings, spec).rates.control_hz
            if tick_count(settings.duration_s, rate) < 1:  # as `hil up`: a run of no tick
                raise ControllerConfigError(too_short(settings.duration_s, rate))
    check_shared_bus(settings)
    return settings


def check_shared_bus(settings: Settings) -> None:
    """Open and close the one bus all runs would share (``--can``, a SocketCAN interface):
    one that cannot be opened (no such interface, no SocketCAN in this kernel) is refused with
    the line its emulator would print (:func:`hal.bus.open_bus`) before any run, instead of
    failing every run; one that opens and may hold hardware is warned of (an emulated DSP
    starts on it). Private per-run buses are each opened by their own run."""
    from hal.bus import open_bus, resolve_spec
    from rt_controller.rig.options import emulator_bus_warning

    if settings.private_buses():
        return
    cfg = settings.base_config()
    if settings.hardware_profile() == "cia402":  # classic frames, at the drives' bit rate
        bus = open_bus(settings.shared_bus(), bitrate=cfg.cia402.bitrate, fd=False)
    else:
        bus = open_bus(settings.shared_bus())
    bus.shutdown()
    if (warning := emulator_bus_warning(resolve_spec(settings.shared_bus()))) is not None:
        print(f"hil experiment: warning: {warning}", file=sys.stderr)


def run_on(
    cl: Cluster, args: argparse.Namespace, settings: Settings, err: Console, progress: Progress
) -> int:
    """Write the runs' configurations, run them on the cluster ``cl`` and write the report."""
    from rt_controller.commands.output import output_dir
    from rt_controller.rig.experiment import prepare
    from rt_controller.rig.experiment_cluster import sweep
    from rt_controller.rig.experiment_report import clear_earlier, write_outputs
    from rt_controller.rig.supervise import RigInterrupted, signals_deferred, supervised

    out = settings.out
    output_dir(out, "--out")  # before any run: a file or an unwritable place is one line
    if args.force:  # an earlier experiment's results must not pass for this one's
        gone = clear_earlier(settings)
        if gone:
            err.print(f"--force: removed the earlier experiment's {', '.join(gone)}")
    with progress.stage(f"writing the runs' configurations into {out}"):
        runs_by_exp, runs = prepare(settings)
    jobs = settings.effective_jobs()
    at_once = f", {jobs} at a time" if jobs > 1 else ""
    if settings.scheduler:
        at_once = f", on {settings.scheduler}" if settings.parallel() else ", one at a time"
    what = f"{settings.clock}, {settings.hardware_profile()} profile{at_once}"
    err.print(f"hil experiment {args.which}: {len(runs)} runs ({what}) -> {out}")
    interrupted: RigInterrupted | None = None
    res: dict[str, Any] | None = None
    try:
        with supervised():
            try:
                sweep(cl, runs, settings, err)
            except RigInterrupted as exc:
                interrupted = exc
            finally:  # a partial sweep (failure, signal) is written up as far as it went;
                # a stop signal meanwhile waits for the write-up (one more after the first:
                # dropped, the experiment is stopping already)
                with (
                    signals_deferred(deliver=interrupted is None),
                    progress.stage(f"writing report.md, results.json and the figures into {out}"),
                ):
                    res = write_outputs(settings, runs_by_exp, runs, command_line(args, out))
    except RigInterrupted as exc:  # the signal held during the write-up
        interrupted = exc
    if interrupted is not None:
        print(f"hil experiment: {interrupted}: partial results in {out}", file=sys.stderr)
        if args.json and res is not None:  # a reader of stdout: the results as far as they went
            print(strict_json.dumps(res))
        return interrupted.exit_code
    for f in res["failures"]:
        print(
            f"hil experiment: run {f['run']} ({f['label']}) failed: {f['error']}", file=sys.stderr
        )
    for r in runs.values():  # not run for a known reason (a shared process died): said
        if r.status == "pending" and r.error:
            print(f"hil experiment: run {r.spec.name} ({r.spec.label}) {r.error}", file=sys.stderr)
    not_run = [r.spec.name for r in runs.values() if r.status == "pending" and not r.error]
    if not_run:
        print(f"hil experiment: not run: {', '.join(not_run)}", file=sys.stderr)
    if args.json:
        print(strict_json.dumps(res))
    else:
        print_tables(res)
    return 1 if res["failures"] or any(r.status != "ok" for r in runs.values()) else 0


def print_tables(res: dict[str, Any]) -> None:
    """The J tables for people, on stdout."""
    from rich.table import Table

    from rt_controller.commands.output import stdout_console
    from rt_controller.rig.experiment_markdown import noise_words

    console = stdout_console()
    for exp, key_title in (("fig3", "law"), ("fig4", "T (s)")):
        if exp in res:
            table = Table(title=f"{exp}: J")
            table.add_column(key_title)
            table.add_column("J", justify="right")
            for k, v in res[exp]["J"].items():
                table.add_row(k, "—" if v is None else f"{v:.4f}")  # failed or not run
            console.print(table)
    if "table1" in res:
        t1 = res["table1"]
        noise = noise_words(t1["noise_px"], res.get("camera_model", "analytic"))
        console.print(f"Table I (J, {noise}, seeds {t1['seeds']}):")
        console.print(t1["markdown"], markup=False, highlight=False)
    console.print(f"report: {res['report']}", markup=False, highlight=False)
    sys.stdout.flush()
