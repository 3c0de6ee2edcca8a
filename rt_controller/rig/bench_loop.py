"""``hil bench loop``: the whole rig in real time at several control rates, plus lockstep speed.

For each rate the three processes run for ``duration`` seconds; the numbers come from the
controller's MCAP log: wake-up lateness, cycle time (read + solve + write), deadline misses and
the end-to-end latency from a joint-state frame's arrival to the torque frame it caused. The
footprint of each process comes from ``/proc`` while it runs (:mod:`rt_controller.rig.footprint`):
peak RSS (anonymous and file-backed), peak locked memory, peak thread count, and CPU % of one
core over the controller's steady second half, per thread name too; the controller's busy-wait
before each deadline (``controller.spin_us``) is reported apart (``spin_cpu_percent``) and
``cpu_percent_excluding_spin`` is the rest.

With ``profile="cia402"`` each rate (and the lockstep run) runs twice back to back, the ``dsp``
profile first, so both profiles' figures come from the same window of the host's load: the
CiA 402 runs add ``canopen`` (SYNC jitter, SYNC-to-TPDO, PDO round trip, torque-to-effect,
from the log's raw frames: :mod:`rt_controller.logtools.canopen_timing`) and ``compare`` puts
the headline figures of both side by side.
"""

from __future__ import annotations

import contextlib
import math
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from hal.config import RigConfig, load_config
from rt_controller.config_rules import apply_overrides, config_toml
from rt_controller.logtools.canopen_timing import log_timing
from rt_controller.logtools.reader import read_log
from rt_controller.rig.footprint import FootprintSampler
from rt_controller.rig.options import RigOptions
from rt_controller.rig.processes import run_rig
from rt_controller.sample_stats import summary_stats

DEFAULT_RATES = (50.0, 200.0, 500.0, 1000.0)


def _rate_config(cfg: RigConfig, rate: float) -> RigConfig:
    rcfg = apply_overrides(cfg, rate=rate)
    return rcfg.with_overrides({"rates.state_hz": min(cfg.rates.state_hz, rcfg.rates.physics_hz)})


def _profile_config(cfg: RigConfig, profile: str | None) -> RigConfig:
    return cfg if profile is None else cfg.with_overrides({"hardware.profile": profile})


def _write_toml(cfg: RigConfig, path: Path) -> None:
    path.write_text(config_toml(cfg))


def _monitor(port: int | None) -> dict[str, Any]:
    return {"monitor": port is not None, "monitor_port": port}


def rate_files(rate: float, profile: str | None = None) -> tuple[str, str]:
    """The config and log a run at ``rate`` writes in the bench's folder."""
    tag = "" if profile is None else f"{profile}-"  # both profiles' runs side by side
    return f"rig-{tag}{rate:g}.toml", f"loop-{tag}{rate:g}.mcap"


def lockstep_files(profile: str | None = None) -> tuple[str, str]:
    """The config and log of the lockstep run."""
    tag = "" if profile is None else f"-{profile}"
    return f"rig-lockstep{tag}.toml", f"lockstep{tag}.mcap"


def bench_files(rates: tuple[float, ...], lockstep: bool, profile: str = "dsp") -> list[str]:
    """Every file :func:`bench_loop` writes in its folder (``--keep``), to check up front."""
    profiles: tuple[str | None, ...] = ("dsp", "cia402") if profile == "cia402" else (None,)
    out = [n for p in profiles for r in rates for n in rate_files(r, p)]
    return out + [n for p in profiles if lockstep for n in lockstep_files(p)]


def bench_rate(
    cfg: RigConfig,
    rate: float,
    duration: float,
    law: str,
    workdir: Path,
    monitor_port: int | None = None,
    profile: str | None = None,
) -> dict:
    """One real-time run at ``rate``; statistics from its log. ``monitor_port``: also run
    ``hil monitor`` on that port (connect a Foxglove client to measure its cost);
    ``profile``: the hardware profile (None: the configuration's)."""
    rcfg = _profile_config(_rate_config(cfg, rate), profile)
    name = rcfg.hardware.profile
    conf, log = (workdir / n for n in rate_files(rate, profile))
    _write_toml(rcfg, conf)
    with FootprintSampler() as sampler:
        summary = run_rig(
            RigOptions(
                config=str(conf),
                law=law,
                duration_s=duration,
                lockstep=False,
                log=log,
                **_monitor(monitor_port),
            )
        )
    loaded = read_log(log)
    c = loaded.cycles
    ticks = int(c["tick"].size)
    misses = int(np.sum(c["deadline_miss"]))
    missed_periods = int(np.sum(c["missed_periods"]))
    return {
        "rate_hz": rate,
        "profile": name,
        "law": law,
        "ticks": ticks,
        "deadline_misses": misses,
        "miss_percent": 100.0 * misses / max(1, ticks + missed_periods),
        "missed_periods": missed_periods,
        "lateness_us": summary_stats(c["lateness_us"]),
        "cycle_us": summary_stats(c["cycle_us"]),
        "solve_us": summary_stats(c["solve_us"]),
        "law_us": _law_stats(c, law),
        "e2e_us": summary_stats(c["e2e_us"]) if "e2e_us" in c else None,
        "predict_ms": _ran_stats(c, "predict_ms", law),
        "f_predict_ms": _ran_stats(c, "f_predict_ms", law),
        "f_final_norm": summary.get("f_final_norm"),
        "fallbacks": summary.get("fallbacks"),
        "late_states": summary.get("late_states"),
        "watchdog_trips": summary.get("watchdog_trips"),
        "dsp_faults": summary.get("dsp_faults"),
        "drive_ticks": summary.get("drive_ticks"),
        "problems": _problems(summary),
        "log": str(log),
        "footprint": footprint(sampler, duration, summary),
        "canopen": canopen_figures(loaded) if name == "cia402" else None,
    }


def _problems(summary: dict[str, Any]) -> list[str]:
    """The run's problems, and a ``--monitor-port`` monitor that failed (a port in use): the
    figures were then taken without the live view they were asked with."""
    problems = list(summary.get("problems") or [])
    if summary.get("monitor_error"):
        problems.append(f"hil monitor failed, no live view ran: {summary['monitor_error']}")
    return problems


def canopen_figures(log: Any) -> dict[str, Any] | None:
    """The CANopen timing of a cia402 run's log (:func:`log_timing`), without the per-frame
    lists (the EMCYs are kept: a fault in a bench run matters)."""
    timing = log_timing(log)
    if timing is None:
        return None
    timing.pop("drive_states", None)
    return timing


COMPARED = ("lateness_us", "cycle_us", "e2e_us")
"""The loop figures both profiles have, compared per rate."""


def compare(dsp: dict[str, Any], cia402: dict[str, Any]) -> dict[str, Any]:
    """One rate's headline figures of both profiles, side by side (median and p99, µs)."""

    def pick(run: dict[str, Any]) -> dict[str, Any]:
        out = {k: _median_p99(run.get(k)) for k in COMPARED}
        out["deadline_misses"] = run.get("deadline_misses")
        out["clean"] = not run.get("problems")
        return out

    row: dict[str, Any] = {"rate_hz": dsp["rate_hz"], "dsp": pick(dsp), "cia402": pick(cia402)}
    co = cia402.get("canopen") or {}
    row["cia402"].update(
        sync_period_error_us=_median_p99((co.get("sync") or {}).get("period_error_us")),
        sync_to_tpdo_us=_median_p99(co.get("sync_to_tpdo_us")),
        pdo_round_trip_us=_median_p99(co.get("pdo_round_trip_us")),
        torque_to_effect_us=_median_p99(co.get("torque_to_effect_us")),
    )
    return row


def _median_p99(stats: dict[str, float] | None) -> dict[str, float] | None:
    return None if stats is None else {"median": stats["median"], "p99": stats["p99"]}


def _law_stats(c: dict, law: str) -> dict | None:
    """The law's own solve time per tick that ran it (``law_us``; RHC: the C/GMRES update,
    comparable with ``hil bench solver``), or None for a closed-form law."""
    if law != "rhc" or "law_us" not in c:
        return None
    ran = np.asarray(c["law"]) == "rhc"
    return summary_stats(np.asarray(c["law_us"], dtype=float)[ran])


def _ran_stats(c: dict, name: str, law: str) -> dict | None:
    """Statistics of a per-tick age the controller compensated, over the ticks that ran the
    law (``predict_ms``, ``f_predict_ms``); None in a log without it."""
    if name not in c:
        return None
    ran = np.asarray(c["law"]) == law
    return summary_stats(np.asarray(c[name], dtype=float)[ran])


def footprint(sampler: FootprintSampler, duration: float, summary: dict) -> dict[str, Any]:
    """Per process: peaks and CPU (:meth:`FootprintSampler.summary`); for the controller also
    the CPU of its spin window, measured by the daemon (``spin_s``), and the rest."""
    out = sampler.summary(steady_s=duration / 2)
    ctl = out.get("controller")
    spin_s = summary.get("spin_s")
    if ctl is not None and spin_s is not None and duration > 0:
        ctl["spin_cpu_percent"] = 100.0 * spin_s / duration
        total = ctl.get("cpu_percent")
        ctl["cpu_percent_excluding_spin"] = (
            None if total is None else max(0.0, total - ctl["spin_cpu_percent"])
        )
    return out


def bench_lockstep(
    cfg: RigConfig, duration: float, law: str, workdir: Path, profile: str | None = None
) -> dict:
    """Wall time of a lockstep run of ``duration`` simulated seconds (all processes)."""
    cfg = _profile_config(cfg, profile)
    name = cfg.hardware.profile
    conf, log = (workdir / n for n in lockstep_files(profile))
    _write_toml(cfg, conf)
    t0 = time.perf_counter()
    summary = run_rig(
        RigOptions(
            config=str(conf),
            law=law,
            duration_s=duration,
            lockstep=True,
            log=log,
        )
    )
    wall = time.perf_counter() - t0
    loaded = read_log(log)
    c = loaded.cycles
    t = c["t_ns"]
    loop_wall = (t[-1] - t[0]) / 1e9 if t.size > 1 else math.nan
    sim = duration
    return {
        "profile": name,
        "law": law,
        "sim_s": sim,
        "ticks": summary.get("ticks"),
        "wall_s_total": wall,
        "wall_s_loop": loop_wall,
        "wall_s_outside_loop": wall - loop_wall,
        "speedup_total": sim / wall,
        "speedup_loop": sim / loop_wall if loop_wall > 0 else math.nan,
        "period_us": lockstep_period_profile(c),
        "J": summary.get("J"),
        "canopen": canopen_figures(loaded) if name == "cia402" else None,
    }


PROFILE_PHASES = {"features_wait": "read_us", "solve": "solve_us", "write": "write_us"}
"""Figure of :func:`lockstep_period_profile` -> the cycle record's field it is the median of."""


def lockstep_period_profile(cycles: dict[str, np.ndarray]) -> dict[str, float]:
    """Where one lockstep period's wall time goes (medians over the run, microseconds; the
    period itself as ``period_median`` and ``period_p99``), from the
    controller's own cycle records: ``features_wait`` (Sync received until this period's
    features arrived: the DSP's pose -> vision -> controller over zenoh), ``solve`` (the law),
    ``write`` (torque frame out), and ``dsp_and_can`` (torque frame out until the next Sync is
    received: the DSP's physics and state frames, both CAN directions, the recorder hand-off).
    """
    t = cycles["t_ns"]
    if t.size < 2:
        return {}
    period = np.diff(t) / 1e3
    cycle = cycles["cycle_us"][:-1]
    p = summary_stats(period, ("median", "p99"))
    return {
        "period_median": p["median"],
        "period_p99": p["p99"],
        **{name: _median(cycles[field]) for name, field in PROFILE_PHASES.items()},
        "dsp_and_can": _median(period - cycle),
    }


def _median(values: np.ndarray) -> float:
    return summary_stats(values, ("median",))["median"]


def bench_loop(
    cfg: RigConfig | None = None,
    *,
    rates: tuple[float, ...] = DEFAULT_RATES,
    duration: float = 10.0,
    law: str = "rhc",
    lockstep_duration: float = 10.0,
    monitor_port: int | None = None,
    keep: Path | None = None,
    host_probe_s: float = 5.0,
    profile: str = "dsp",
) -> dict[str, Any]:
    """The JSON object ``hil bench loop`` prints. ``keep``: write the runs' logs and configs
    there (kept) instead of a temporary folder. ``host_probe_s``: first measure the host's own
    wake-up lateness that long (``host``, :func:`~rt_controller.rig.bench_host.bench_host`),
    so the run's figures come with the floor under them; 0 skips it. ``profile="cia402"``:
    every run twice, ``dsp`` then ``cia402`` (see the module docstring); ``rates`` and
    ``lockstep`` are then the cia402 runs, ``dsp_rates`` and ``dsp_lockstep`` the dsp's."""
    from rt_controller.rig.bench_host import bench_host

    cfg = cfg or load_config()
    host = bench_host(host_probe_s) if host_probe_s > 0 else None
    with contextlib.ExitStack() as stack:
        work = bench_workdir(stack, keep, "hil-bench-")
        if profile == "cia402":
            both = _bench_both(
                cfg, rates, duration, law, lockstep_duration, work, host, monitor_port
            )
            return _logs_if_kept({**both, "can_frame_us": can_frame_us()}, keep)
        runs = [bench_rate(cfg, r, duration, law, work, monitor_port) for r in rates]
        lock = bench_lockstep(cfg, lockstep_duration, law, work) if lockstep_duration > 0 else None
    out = {
        "profile": "dsp",
        "duration_s": duration,
        "rates": runs,
        "lockstep": lock,
        "monitor_port": monitor_port,
        "host": host,
        "can_frame_us": can_frame_us(),
        "machine": machine(),
    }
    return _logs_if_kept(out, keep)


def can_frame_us() -> dict[str, float]:
    """The per-frame CAN encode/decode and SecOC sign/verify cost, whatever the profile."""
    from hal.can_codec import bench_codec
    from hal.secoc import bench_mac

    return {**bench_mac(), **bench_codec(2000)}


def _logs_if_kept(out: dict[str, Any], keep: Path | None) -> dict[str, Any]:
    """A run's ``log`` names its MCAP file only under ``keep``: without it the temporary
    folder is gone when the bench returns, and a path to nothing would mislead."""
    if keep is None:
        for run in out["rates"] + out.get("dsp_rates", []):
            run["log"] = None
    return out


def _bench_both(
    cfg: RigConfig,
    rates: tuple[float, ...],
    duration: float,
    law: str,
    lockstep_duration: float,
    work: Path,
    host: dict[str, Any] | None,
    monitor_port: int | None,
) -> dict[str, Any]:
    """Each rate (and the lockstep run) with the dsp profile, then at once the cia402."""
    dsp_runs, runs = [], []
    for r in rates:
        dsp_runs.append(bench_rate(cfg, r, duration, law, work, monitor_port, profile="dsp"))
        runs.append(bench_rate(cfg, r, duration, law, work, monitor_port, profile="cia402"))
    dsp_lock = lock = None
    if lockstep_duration > 0:
        dsp_lock = bench_lockstep(cfg, lockstep_duration, law, work, profile="dsp")
        lock = bench_lockstep(cfg, lockstep_duration, law, work, profile="cia402")
    return {
        "profile": "cia402",
        "duration_s": duration,
        "compare": [compare(d, c) for d, c in zip(dsp_runs, runs, strict=True)],
        "rates": runs,
        "dsp_rates": dsp_runs,
        "lockstep": lock,
        "dsp_lockstep": dsp_lock,
        "monitor_port": monitor_port,
        "host": host,
        "machine": machine(),
    }


def bench_workdir(stack: contextlib.ExitStack, keep: Path | None, prefix: str) -> Path:
    """Where a bench writes its runs: ``keep`` (created, kept), else a temporary folder that
    ``stack`` removes."""
    if keep is None:
        return Path(stack.enter_context(tempfile.TemporaryDirectory(prefix=prefix)))
    keep.mkdir(parents=True, exist_ok=True)
    return keep


def machine() -> dict[str, Any]:
    """The host under a bench's figures: CPUs and load averages (other work skews them)."""
    return {
        "cpus": os.cpu_count(),
        "load": dict(zip(("1min", "5min", "15min"), os.getloadavg(), strict=True)),
    }
