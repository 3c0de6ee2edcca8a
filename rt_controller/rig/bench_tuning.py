"""``hil bench tuning``: in a realtime run, how long a parameter set takes from the client's
request to the tick at which it is in force, and what a law switch rhc -> ioc -> rhc costs the
switching tick's decide phase.

The rig runs as ``hil up`` (realtime) in a child process; this process is the client (the signed
link of :mod:`rt_controller.calibration.link`, as ``hil param``). Latency = the outcome's
``t_ns`` (the loop's monotonic clock at the tick boundary; the same clock on this host) minus
the client's monotonic time just before it sent the request.
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hal.secoc import load_key_file, write_key_file
from hal.zenoh_session import free_loopback_port, open_session
from rt_controller.calibration.link import request
from rt_controller.sample_stats import summary_stats


def bench_tuning(workdir: Path, *, requests: int = 50, gap_s: float = 0.1) -> dict[str, Any]:
    """Run the rig, make ``requests`` kp sets and one law switch rhc -> ioc -> rhc; the JSON."""
    from rt_controller.logtools.reader import read_log

    workdir.mkdir(parents=True, exist_ok=True)
    key_file = write_key_file(workdir / "bench.key", overwrite=True)
    key = load_key_file(key_file)
    ep = f"tcp/127.0.0.1:{free_loopback_port()}"
    log = workdir / "tuning.mcap"
    duration = 20.0 + requests * (gap_s + 0.1)
    up = subprocess.Popen(
        [sys.executable, "-m", "rt_controller.cli", "up", "--law", "rhc", "--duration",
         f"{duration:g}", "--zenoh-endpoint", ep, "--key-file", str(key_file), "--log", str(log),
         "--force", "--json"],  # the bench's own log in its workdir, as its key: replaced
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    lat_ns: list[int] = []
    switch_ticks: list[int] = []
    period_s = 0.02
    try:
        session = open_session(listen=False, endpoint=ep)
        try:
            deadline = time.monotonic() + 120
            while True:
                try:
                    request(session, key, "get", timeout_s=1.0)
                    break
                except Exception:
                    if time.monotonic() > deadline or up.poll() is not None:
                        raise
            time.sleep(2.0)  # past arming
            for i in range(requests):
                kp = 0.13 + 0.001 * (i % 2)
                t0 = time.monotonic_ns()
                out = request(session, key, "set", changes={"gains.kp": kp}, timeout_s=10.0)
                lat_ns.append(int(out["outcome"]["t_ns"]) - t0)
                time.sleep(gap_s)
            for law in ("ioc", "rhc"):
                out = request(session, key, "set", changes={"controller.law": law})
                switch_ticks.append(int(out["outcome"]["tick"]))
                time.sleep(1.0)
        finally:
            session.close()
        up.communicate(timeout=duration + 120)
    finally:
        if up.poll() is None:
            up.kill()
            up.communicate()
    loaded = read_log(log, raw=False)
    period_s = 1.0 / loaded.config.rates.control_hz if loaded.config else period_s
    ticks = np.asarray(loaded.cycles["tick"])
    solve = np.asarray(loaded.cycles["solve_us"], dtype=float)
    figures = tuning_figures(lat_ns, switch_ticks, ticks, solve, period_s)
    return {**figures, "rig_exit": up.returncode, "log": str(log)}


def tuning_figures(
    lat_ns: Sequence[int],
    switch_ticks: list[int],
    ticks: np.ndarray,
    solve_us: np.ndarray,
    period_s: float,
) -> dict[str, Any]:
    """The bench's figures from its samples: request-to-effect latency (ms and control periods)
    and the decide phase's time at the law switches against the other ticks; statistics of the
    finite samples (:mod:`rt_controller.sample_stats`), NaN when there are none."""
    at = [int(i[0]) for k in switch_ticks if (i := np.flatnonzero(ticks == k)).size]
    ms = summary_stats(np.asarray(lat_ns, dtype=float) / 1e6)
    ordinary = summary_stats(np.delete(solve_us, at), ("median", "p99"))
    return {
        "requests": len(lat_ns),
        "request_to_effect_ms": ms,
        "request_to_effect_periods": {k: ms[k] / 1e3 / period_s for k in ("median", "p99")},
        "within_two_periods": bool(ms["p99"] / 1e3 <= 2 * period_s),
        "law_switch": {
            "ticks": switch_ticks,
            "decide_us_at_switch": [float(solve_us[i]) for i in at],
            "decide_us_ordinary": ordinary,
        },
    }


__all__ = ["bench_tuning", "tuning_figures"]
