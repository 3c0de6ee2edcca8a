"""``hil bench host``: how late this host wakes a real-time thread, with nothing of the rig running.

The measurement of ``cyclictest``: on every CPU a probe process, pinned to it and at SCHED_FIFO
priority 99 (above the controller's and the DSP's), sleeps until each period's absolute release
and records how late it woke. Nothing in the guest outranks it, so a wake-up that is late by
milliseconds means the CPU itself was not there: a virtual machine's vCPU descheduled by its
hypervisor (steal time), or firmware. It is the floor under ``hil bench loop``'s lateness: a
controller cannot be released more punctually than the host wakes a thread, and a 1 kHz loop
cannot have zero misses on a host that pauses a CPU for 10 ms every few seconds.

Each probe reports its wake-ups, lateness (median, p99, max), the wake-ups later than 100 µs
and 1 ms and its latest ones (``at_ms`` from its start); ``steal_percent`` is the share of the
CPUs' time the hypervisor took over the run (``/proc/stat``). A probe that may not use
SCHED_FIFO runs at normal priority and says so.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from typing import Any

import numpy as np

from hal import strict_json
from rt_controller.errors import ControllerError
from rt_controller.runtime.cadence import Cadence, Clock, MonotonicClock
from rt_controller.runtime.host_steal import cpu_ticks, steal_percent
from rt_controller.sample_stats import summary_stats

PROBE_PRIORITY = 99
"""SCHED_FIFO priority of a probe (above every process of the rig)."""
LATE_US = (100, 1000)
"""Wake-ups later than these are counted (``late_over_100us``, ``late_over_1000us``)."""
WORST = 10
"""The latest wake-ups each probe lists (time from its start, lateness)."""


def probe(
    cpu: int, duration_s: float, period_us: int, *, clock: Clock | None = None
) -> dict[str, Any]:
    """Run one probe in this process: pinned to ``cpu`` at SCHED_FIFO (if allowed), released
    every ``period_us`` for ``duration_s`` by the controller's own :class:`Cadence` (releases a
    pause swallowed are skipped, never run in a burst), sleeping to each release without the
    controller's spin window; its figures. ``clock`` (tests) replaces the real clock, and then
    nothing real-time is applied."""
    from rt_controller.runtime.realtime import RtReport, apply_realtime

    if clock is None:
        rt = apply_realtime(PROBE_PRIORITY, cpu, lock_memory=False)
        clock = MonotonicClock(spin_ns=0)
    else:
        rt = RtReport()
    cadence = Cadence(period_us * 1000, clock)
    start = clock.now_ns()
    end = start + round(duration_s * 1e9)
    late: list[int] = []
    at: list[int] = []
    while True:
        tick = cadence.wait()
        if tick.release_ns > end:
            break
        late.append(tick.wake_lateness_ns)  # for the release it slept to, as the host woke
        at.append((tick.release_ns if tick.asked_ns is None else tick.asked_ns) - start)
    late_us, at_ms = np.asarray(late) / 1e3, np.asarray(at) / 1e6
    worst = np.argsort(late_us)[-WORST:][::-1]
    fifo = [a for a in rt.applied if a.startswith("SCHED_FIFO")]
    refused = [w for w in rt.warnings if "SCHED_FIFO" in w]
    return {
        "cpu": cpu,
        "scheduling": fifo[0] if fifo else f"normal ({refused[0] if refused else 'not asked'})",
        "wakeups": len(late),
        "lateness_us": summary_stats(late_us),
        **{f"late_over_{t}us": int(np.sum(late_us > t)) for t in LATE_US},
        "worst": [
            {"at_ms": round(float(at_ms[i]), 3), "late_us": round(float(late_us[i]), 1)}
            for i in worst
        ],
    }


def bench_host(
    duration_s: float = 10.0, period_us: int = 1000, cpus: list[int] | None = None
) -> dict[str, Any]:
    """One probe per CPU (``cpus``, default every CPU this process may use), all at once, each
    in its own process; their figures and the steal over the run."""
    if not (duration_s > 0 and math.isfinite(duration_s)) or period_us < 50:
        raise ControllerError("bench host: duration must be > 0 and period at least 50 us")
    if duration_s * 1e6 < period_us:  # no release would fall in the run: figures of nothing
        raise ControllerError(
            f"bench host: --duration {duration_s:g} s is shorter than one --period-us "
            f"({period_us} us): no wake-up to measure"
        )
    cpus = sorted(os.sched_getaffinity(0)) if cpus is None else cpus
    before = cpu_ticks()
    procs: list[subprocess.Popen] = []
    try:  # a Ctrl-C while the probes start stops those already started too
        for cpu in cpus:
            args = [sys.executable, "-m", "rt_controller.rig.bench_host", str(cpu)]
            args += [repr(duration_s), str(period_us)]
            procs.append(
                subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            )
        probes = [_probe_report(cpu, p) for cpu, p in zip(cpus, procs, strict=True)]
    finally:  # Ctrl-C or a failed probe: the others must not run on at priority 99
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.communicate()
    steal = steal_percent(before, cpu_ticks())
    return {
        "duration_s": duration_s,
        "period_us": period_us,
        "steal_percent": steal,
        "probes": probes,
    }


def _probe_report(cpu: int, proc: subprocess.Popen) -> dict[str, Any]:
    """The figures a probe process printed, once it ended."""
    out, err = proc.communicate()
    if proc.returncode != 0 or not out.strip():
        raise ControllerError(f"bench host: the probe on CPU {cpu} failed: {err.strip()}")
    return json.loads(out)


def main(argv: list[str]) -> int:
    """``python -m rt_controller.rig.bench_host CPU DURATION_S PERIOD_US``: one probe, JSON."""
    print(strict_json.dumps(probe(int(argv[0]), float(argv[1]), int(argv[2]))))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
