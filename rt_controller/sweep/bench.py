"""``hil bench sweep``: runs per second of the sweep engines, serial and on Dask.

For each engine the same runs (the paper scenario, one point, ``runs`` repetitions with their
own noise seeds) go through the in-process serial loop, then a local cluster of 1 worker, then
one of ``workers`` (default: one per CPU). Every worker runs one warm-up task first (imports,
numba's cache), which is not timed; the timed part is submit-to-last-result. Reported:
runs/s of each, ``scaling`` = all / 1 worker, ``efficiency`` = all / (workers x serial), and
whether the rows agree with the serial loop bit for bit (``identical``; simulate only: a rig
run's J depends on nothing else either, but is checked within 1e-9 relative).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from rt_controller.sweep.engines import Engine, run_task
from rt_controller.sweep.executor import machine_workers, open_cluster
from rt_controller.sweep.spec import RunTask, SweepSpecError, spec_from_dict


def bench_tasks(engine: str, runs: int, duration_s: float, law: str) -> list[RunTask]:
    """The bench's runs as a sweep's; a setting a sweep refuses names the bench's option."""
    try:
        spec = spec_from_dict(
            {
                "study": {"duration_s": duration_s, "repetitions": runs, "timeout_s": 600.0},
                "base": {  # the rig's rendering camera's noise is its sensor's, seeded per run
                    "controller": {"law": law},
                    "camera": {"noise_px": 0.5} if engine == "simulate" else {},
                },
            }
        )
    except SweepSpecError as exc:
        option = "--rig-duration" if engine == "rig" else "--duration"
        raise SweepSpecError(f"{option} {duration_s:g} (runs {runs}): {exc}") from None
    return spec.tasks(engine)


def _warm(plant: Any, task: RunTask) -> bool:
    """Run on every worker before the clock starts."""
    return run_task(task, plant)["status"] == "ok"


def _timed_cluster(
    workers: int, tasks: list[RunTask], warm: RunTask, plant: Any
) -> tuple[float, list[dict[str, Any]]]:
    from distributed import wait

    cl = open_cluster(workers)
    try:
        cl.client.wait_for_workers(workers, timeout=120)
        cl.client.run(_warm, plant, warm)
        engine = Engine(plant)
        t0 = time.perf_counter()
        futures = [cl.client.submit(engine, t, pure=False) for t in tasks]
        wait(futures)
        elapsed = time.perf_counter() - t0
        rows = cl.client.gather(futures)
    finally:
        cl.close()
    return elapsed, rows


def _median_wall(rows: list[dict[str, Any]]) -> float:
    """Median of the runs' own wall time (inside the task: what a worker spends per run)."""
    import statistics

    return statistics.median(r["wall_s"] for r in rows)


def bench_engine(
    engine: str,
    plant: Callable[[Any], Any] | None,
    *,
    runs: int,
    duration_s: float,
    law: str,
    workers: int,
) -> dict[str, Any]:
    tasks = bench_tasks(engine, runs, duration_s, law)
    warm = bench_tasks(engine, 1, min(duration_s, 0.5), law)[0]
    run_task(warm, plant)
    t0 = time.perf_counter()
    serial = [run_task(t, plant) for t in tasks]
    serial_s = time.perf_counter() - t0
    out: dict[str, Any] = {
        "engine": engine,
        "law": law,
        "runs": runs,
        "duration_s": duration_s,
        "serial_runs_per_s": runs / serial_s,
        "serial_run_s_median": _median_wall(serial),
        "failed": sum(r["status"] != "ok" for r in serial),
        "errors": sorted({r["error"] for r in serial if r["error"]})[:3],
    }
    counts = [1] if workers == 1 else [1, workers]
    identical = True
    for n in counts:
        elapsed, rows = _timed_cluster(n, tasks, warm, plant)
        out[f"workers_{n}_runs_per_s"] = runs / elapsed
        out[f"workers_{n}_run_s_median"] = _median_wall(rows)
        out["failed"] += sum(r["status"] != "ok" for r in rows)
        out["errors"] = sorted({*out["errors"], *(r["error"] for r in rows if r["error"])})[:3]
        for a, b in zip(serial, rows, strict=True):
            if engine == "simulate":
                identical &= a["J"] == b["J"] and a["f_final_norm"] == b["f_final_norm"]
            else:
                identical &= abs(a["J"] - b["J"]) <= 1e-9 * max(1.0, abs(a["J"]))
    top = out[f"workers_{counts[-1]}_runs_per_s"]
    out["workers"] = counts[-1]
    out["scaling"] = top / out["workers_1_runs_per_s"]
    out["efficiency"] = top / (counts[-1] * out["serial_runs_per_s"])
    out["efficiency_1_worker"] = out["workers_1_runs_per_s"] / out["serial_runs_per_s"]
    out["identical"] = identical
    return out


def bench_sweep(
    plant: Callable[[Any], Any],
    *,
    runs: int = 40,
    duration_s: float = 6.0,
    law: str = "rhc",
    workers: int | None = None,
    rig_runs: int = 4,
    rig_duration_s: float = 2.0,
) -> dict[str, Any]:
    n = machine_workers() if workers is None else workers
    result: dict[str, Any] = {"cpus": machine_workers(), "engines": []}
    result["engines"].append(
        bench_engine("simulate", plant, runs=runs, duration_s=duration_s, law=law, workers=n)
    )
    if rig_runs > 0:
        result["engines"].append(
            bench_engine("rig", plant, runs=rig_runs, duration_s=rig_duration_s, law=law, workers=n)
        )
    return result
