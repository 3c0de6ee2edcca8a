"""``hil bench host``: the probe's accounting on a fake clock, and the real probes' report."""

from __future__ import annotations

import json
import os

import pytest

from rt_controller.cli import main
from rt_controller.errors import ControllerError
from rt_controller.rig.bench_host import bench_host, probe

US = 1_000


class PausingClock:
    """A :class:`~rt_controller.runtime.cadence.Clock` whose sleeps wake exactly on time,
    except the ones listed in ``pauses`` (sleep number -> extra nanoseconds: the CPU was away
    that long)."""

    def __init__(self, pauses: dict[int, int]) -> None:
        self.t = 1_000_000 * US
        self.sleeps = 0
        self.pauses = pauses

    def now_ns(self) -> int:
        return self.t

    def sleep_until(self, deadline_ns: int, idle=None) -> None:
        self.t = max(self.t, deadline_ns) + self.pauses.get(self.sleeps, 0)
        self.sleeps += 1


def test_a_probe_counts_late_wakeups_and_skips_the_releases_a_pause_swallowed():
    """1 ms releases for 20 ms; the 5th wake-up comes 3.5 ms late, in the 8 ms release's
    period. As the controller's cadence does, that wake-up takes the 8 ms release and the 6
    and 7 ms ones are skipped; the probe reports it as 3.5 ms late for the 5 ms release it
    slept to (the host's latency), and every other wake-up is on time: no burst after it."""
    clock = PausingClock({4: 3_500 * US})
    out = probe(0, 0.02, 1000, clock=clock)
    assert out["scheduling"] == "normal (not asked)"
    assert out["late_over_1000us"] == 1 and out["late_over_100us"] == 1
    assert out["lateness_us"]["max"] == 3500.0 and out["lateness_us"]["median"] == 0.0
    assert out["worst"][0] == {"at_ms": 5.0, "late_us": 3500.0}
    assert all(w["late_us"] == 0.0 for w in out["worst"][1:])
    assert out["wakeups"] == 20 - 3


def test_bench_host_runs_one_probe_per_cpu_and_reports_each(capsys):
    cpu = min(os.sched_getaffinity(0))
    out = bench_host(0.2, 2000, cpus=[cpu])
    (p,) = out["probes"]
    assert p["cpu"] == cpu and 0 < p["wakeups"] <= 101
    assert p["wakeups"] >= p["late_over_100us"] >= p["late_over_1000us"] >= 0
    assert p["scheduling"].startswith(("SCHED_FIFO priority 99", "normal ("))
    assert out["steal_percent"] is None or out["steal_percent"] >= 0.0
    assert main(["bench", "host", "--duration", "0.1", "--period-us", "5000"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert len(doc["probes"]) == len(os.sched_getaffinity(0)) and doc["period_us"] == 5000


@pytest.mark.parametrize(("duration", "period"), [(0.0, 1000), (1.0, 10)])
def test_bench_host_refuses_a_meaningless_run(duration, period):
    with pytest.raises(ControllerError, match="bench host"):
        bench_host(duration, period)
