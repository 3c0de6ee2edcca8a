"""``hil sweep SPEC.toml``: a study of many runs on Dask (see :mod:`rt_controller.sweep`).

One of the CLI's dispatch modules: it hands the emulator's plant class
(:class:`plant_emulator.world.World`) to the ``simulate`` engine, which the sweep package
itself never imports.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from hal.arguments import bounded_int, path_given


def simulate_plant() -> Any:
    """The plant class of the ``simulate`` engine (also used by ``hil bench sweep``)."""
    from plant_emulator.world import World

    return World


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sweep",
        help="run a study (grid / Monte Carlo over config keys, model mismatch) on Dask",
        description="Expand SPEC.toml (base config, axes, repetitions) into runs, run them on a "
        "Dask cluster (a local one by default) with the simulate or rig engine, and keep one "
        "row per run in DIR/results.parquet and results.csv, plus DIR/report.md. Running the "
        "same spec into the same DIR again skips the finished runs.",
    )
    p.add_argument("spec", metavar="SPEC.toml", help="the study spec")
    p.add_argument(
        "--out",
        type=path_given,
        metavar="DIR",
        help="results folder (default: sweeps/STEM, STEM the spec file's name without .toml)",
    )
    p.add_argument(
        "--engine",
        choices=("simulate", "rig"),
        help="simulate: in-process closed loop (fast); rig: the lockstep processes "
        "(default: study.engine of the spec, else simulate)",
    )
    p.add_argument(
        "--workers",
        type=bounded_int(1, 256, what="--workers"),
        metavar="N",
        help="worker processes of the local cluster (default: one per CPU)",
    )
    p.add_argument(
        "--scheduler",
        metavar="tcp://HOST:8786",
        help="use this existing Dask cluster instead of a local one (its workers need "
        "this package installed)",
    )
    p.add_argument(
        "--keep-logs",
        action="store_true",
        help="keep each run's log in DIR/logs (rig: MCAP; simulate: the trace as Parquet)",
    )
    p.add_argument(
        "--retry-failed",
        action="store_true",
        help="run the failed runs of DIR again (without it a resume skips them and exits 1)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.add_argument("--json", action="store_true", help="print the outcome as one JSON object")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from rt_controller.extras import require_extra

    require_extra("sweep", "this command")
    from rt_controller.commands.output import output_dir, print_summary
    from rt_controller.errors import ControllerConfigError
    from rt_controller.sweep.executor import run_sweep
    from rt_controller.sweep.report import write_report
    from rt_controller.sweep.spec import load_spec

    if args.workers is not None and args.scheduler is not None:
        raise ControllerConfigError(
            "--workers sizes the local cluster; with --scheduler the cluster has its own"
        )
    spec = load_spec(args.spec)
    out = Path(args.out) if args.out else Path("sweeps") / Path(args.spec).stem
    logs = out / "logs" if args.keep_logs else None
    tasks = spec.tasks(args.engine, logs)  # every run's config valid before out is touched
    output_dir(out, "--out")  # a file there is refused before the cluster starts
    outcome = run_sweep(
        spec,
        out,
        engine=args.engine,
        plant=simulate_plant(),
        workers=args.workers,
        scheduler=args.scheduler,
        keep_logs=args.keep_logs,
        retry_failed=args.retry_failed,
        progress=not args.no_progress,
        tasks=tasks,
    )
    report = write_report(out, spec)
    summary = {**outcome.as_dict(), "out": str(out), "report": str(report)}
    print_summary(summary, args.json, f"hil sweep {spec.study.name}")
    if outcome.interrupted:
        print(
            f"hil sweep: interrupted after {outcome.ran} run(s); the finished rows are in "
            f"{out}; the same command resumes",
            file=sys.stderr,
        )
        return 130
    if outcome.kept_failed:
        names = ", ".join(outcome.kept_failed[:5]) + (
            ", ..." if len(outcome.kept_failed) > 5 else ""
        )
        print(
            f"hil sweep: {len(outcome.kept_failed)} failed run(s) in {out} not run again "
            f"({names}); --retry-failed runs them again",
            file=sys.stderr,
        )
    return 1 if outcome.failed or outcome.kept_failed else 0
