"""``hil bench soak``: the realtime rig for a long run, watched for leaks and backlog.

One realtime run of the three processes (the machinery of ``hil up``, :func:`run_rig`) for
``duration`` seconds. Every ``sample_s`` seconds the RSS of each process (controller,
emulator, vision and the controller's recorder process, from ``/proc/PID/status`` through
:class:`~rt_controller.rig.footprint.FootprintSampler`) and the log's size on disk are taken;
the recorder's backlog (bytes of the record stream the recorder process has not read yet,
``backlog_bytes``) comes from the controller's own ``/diagnostics`` records in the log, about
one a second. Reported:
the series, each process's RSS growth after the warm-up (default: the first minute, which holds
numba's compile and the first allocations), its slope, deadline misses and the log's size.
Figures only: nothing is asserted here (a test checks the structure).
"""

from __future__ import annotations

import contextlib
import time
from pathlib import Path
from typing import Any

import numpy as np

from hal.config import RigConfig, load_config
from rt_controller.config_rules import config_toml
from rt_controller.logtools.reader import read_log
from rt_controller.rig.bench_loop import bench_workdir, machine
from rt_controller.rig.footprint import MIB, FootprintSampler
from rt_controller.rig.options import RigOptions
from rt_controller.rig.processes import run_rig


class SoakSampler(FootprintSampler):
    """:class:`FootprintSampler` that also takes the size of ``log`` at each sample."""

    def __init__(self, log: Path, interval_s: float) -> None:
        super().__init__(interval_s=interval_s)
        self.log = log
        self.log_sizes: list[tuple[float, int]] = []

    def sample(self) -> None:
        super().sample()
        with contextlib.suppress(OSError):  # not created yet
            self.log_sizes.append((time.monotonic(), self.log.stat().st_size))


def rss_growth(series: list[tuple[float, float]], warmup_s: float) -> dict[str, float | None]:
    """RSS (MB) at the first sample at or after ``warmup_s`` and at the last one; their
    difference and the least-squares slope in MB per hour over the samples between them.
    None where fewer than two samples lie after the warm-up."""
    after = [(t, mb) for t, mb in series if t >= warmup_s]
    if len(after) < 2:
        return {"from_mb": None, "to_mb": None, "growth_mb": None, "slope_mb_per_h": None}
    t = np.array([a[0] for a in after])
    mb = np.array([a[1] for a in after])
    slope = float(np.polyfit(t, mb, 1)[0]) * 3600.0 if np.ptp(t) > 0 else None
    return {
        "from_mb": float(mb[0]),
        "to_mb": float(mb[-1]),
        "growth_mb": float(mb[-1] - mb[0]),
        "slope_mb_per_h": slope,
    }


def recorder_backlog(diagnostics: list[dict[str, Any]], t0_s: float) -> list[list[float]]:
    """``[t_s, backlog_bytes, dropped]`` of each periodic ``/diagnostics`` record (the final one
    is taken after the run), ``t_s`` on the soak's time axis."""
    out = []
    for rec in diagnostics:
        if rec.get("final"):
            continue
        values = next(
            (s.get("values", {}) for s in rec.get("status", []) if s.get("name") == "recorder"),
            None,
        )
        if values is None or "t_ns" not in rec:
            continue
        t = rec["t_ns"] / 1e9 - t0_s
        backlog = int(values.get("backlog_bytes", 0))
        out.append([round(t, 3), backlog, int(values.get("dropped", 0))])
    return out


def bench_soak(
    cfg: RigConfig | None = None,
    *,
    duration: float = 1800.0,
    sample_s: float = 10.0,
    warmup_s: float = 60.0,
    law: str = "rhc",
    keep: Path | None = None,
) -> dict[str, Any]:
    """The JSON object ``hil bench soak`` prints (see the module docstring). ``keep``: write
    the log and config there instead of a temporary folder. Times are seconds since the
    rig was started (``t_s``)."""
    cfg = cfg or load_config()
    with contextlib.ExitStack() as stack:
        work = bench_workdir(stack, keep, "hil-soak-")
        conf, log = work / "soak.toml", work / "soak.mcap"
        conf.write_text(config_toml(cfg))
        t0 = time.monotonic()
        sampler = SoakSampler(log, sample_s)
        with sampler:
            summary = run_rig(RigOptions(config=str(conf), law=law, duration_s=duration, log=log))
        sampler.sample()  # the rig's processes are gone: only the log's final size
        loaded = read_log(log, raw=False)
        log_bytes = log.stat().st_size
    rss = {
        role: [[round(s.t - t0, 3), round(s.rss / MIB, 3)] for s in series]
        for role, series in sorted(sampler.series.items())
    }
    ticks = int(loaded.cycles["tick"].size) if "tick" in loaded.cycles else 0
    backlog = recorder_backlog(loaded.diagnostics, t0)
    return {
        "duration_s": duration,
        "law": law,
        "rate_hz": cfg.rates.control_hz,
        "sample_s": sample_s,
        "warmup_s": warmup_s,
        "ticks": ticks,
        "deadline_misses": summary.get("deadline_misses"),
        "missed_periods": summary.get("missed_periods"),
        "problems": summary.get("problems") or [],
        "warnings": summary.get("warnings") or [],
        "rss_mb": rss,
        "rss_growth": {role: rss_growth(s, warmup_s) for role, s in rss.items()},
        "peak_rss_mb": {role: max(mb for _, mb in s) for role, s in rss.items()},
        "log": str(log) if keep is not None else None,
        "log_bytes": log_bytes,
        "log_size": [[round(t - t0, 3), size] for t, size in sampler.log_sizes],
        "recorder_backlog": backlog,
        "recorder_backlog_max": max((p for _, p, _ in backlog), default=None),
        "recorder": summary.get("recorder"),
        "machine": machine(),
    }
