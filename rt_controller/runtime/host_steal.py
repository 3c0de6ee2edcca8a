"""The hypervisor's steal time: the share of the CPUs' time a virtual machine's host gave to
others (``/proc/stat``), and what it means for a realtime run.

A realtime run is the paper's experiment only while the rig's processes get the CPUs when
they are due. On a 2-vCPU virtual machine whose host is overcommitted, the emulated DSP, the
camera and the controller are paused for milliseconds at a time; the closed loop then differs
from the lockstep run by more than rounding, and its J with it. The controller measures the
steal over its law ticks so its summary can say so.
"""

from __future__ import annotations

from pathlib import Path

PROC_STAT = Path("/proc/stat")

DISTURBED_STEAL_PERCENT = 10.0
"""Steal over a realtime run from which its J is not comparable with the lockstep run's.

Measured on a 2-vCPU VM, ``hil up --json`` (ioc and rhc, 10 s) against ``hil up --lockstep``:
at 1-4 % steal J was within 0.6 % of lockstep; at 10-23 % from -0.03 to +2.9 %; at 29-39 %
from -4.6 % to +53 % (the camera starved: feature ages of 200 ms)."""


def cpu_ticks(stat: Path = PROC_STAT) -> tuple[int, int] | None:
    """(steal, total) jiffies of all CPUs; None where ``stat`` is not Linux's ``/proc/stat``."""
    try:
        fields = stat.read_text(encoding="ascii").split("\n", 1)[0].split()
    except OSError:
        return None
    if len(fields) < 9 or fields[0] != "cpu":
        return None
    try:
        values = [int(v) for v in fields[1:9]]
    except ValueError:
        return None
    return values[7], sum(values)


def steal_percent(before: tuple[int, int] | None, after: tuple[int, int] | None) -> float | None:
    """The steal between two :func:`cpu_ticks` readings, in percent of the CPUs' time (None
    when either reading is missing or no time passed between them)."""
    if before is None or after is None or after[1] <= before[1]:
        return None
    return 100.0 * (after[0] - before[0]) / (after[1] - before[1])
