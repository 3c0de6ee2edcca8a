"""Per-process footprint from ``/proc``: resident and locked memory, threads, CPU time.

:func:`read_footprint` takes one snapshot of a process (``/proc/PID/status``, ``/proc/PID/stat``
and, per thread, ``/proc/PID/task/TID/stat`` + ``comm``); :class:`FootprintSampler` samples the
children of ``hil up``/``hil bench loop`` (and the controller's recorder process) in a
background thread and turns the series into the
figures ``hil bench loop --json`` reports (:meth:`FootprintSampler.summary`): peak RSS (anonymous
and file-backed), peak locked memory (``VmLck``), peak thread count and CPU % of one core over a
steady window, per process and, for the CPU, per thread name.

Linux only; on any other system (or for a process that is gone) the readers return ``None``.
The parsers take text so unit tests feed them recorded ``/proc`` contents.
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

KIB = 1024
MIB = 1024 * 1024
ROLES = ("controller", "emulator", "vision")
"""The rig's processes, recognised by the ``hil`` subcommand in their command line."""
CHILD_ROLES = {"controller": "recorder"}
"""Processes of a rig process, by its role: the controller's MCAP recorder
(the recorder process)."""


@dataclass(frozen=True)
class Snapshot:
    """One process at one moment (memory in bytes, CPU in clock ticks)."""

    t: float
    rss: int
    rss_anon: int
    rss_file: int
    locked: int
    hwm: int
    threads: int
    cpu_ticks: int
    thread_ticks: dict[str, int] = field(default_factory=dict)
    """CPU ticks summed by thread name (``comm``)."""


def parse_status(text: str) -> dict[str, int]:
    """``/proc/PID/status`` → the ``Vm*``/``Rss*`` sizes in bytes and ``Threads``."""
    out: dict[str, int] = {}
    for line in text.splitlines():
        key, _, value = line.partition(":")
        parts = value.split()
        if not parts:
            continue
        if key.startswith(("Vm", "Rss")) and len(parts) == 2 and parts[1] == "kB":
            out[key] = int(parts[0]) * KIB
        elif key == "Threads":
            out[key] = int(parts[0])
    return out


def parse_stat_cpu(text: str) -> int:
    """``/proc/PID/stat`` (or a task's) → utime + stime in clock ticks.

    The command name (field 2) may hold spaces and parentheses, so fields are counted after
    the last ``)``: state is field 3, utime field 14, stime field 15.
    """
    rest = text[text.rindex(")") + 2 :].split()
    return int(rest[11]) + int(rest[12])


def _read(path: Path) -> str | None:
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError):
        return None


def thread_ticks(pid: int, proc: Path = Path("/proc")) -> dict[str, int]:
    """CPU ticks of each thread of ``pid`` summed by thread name (gone threads are skipped)."""
    out: dict[str, int] = {}
    try:
        tids = os.listdir(proc / str(pid) / "task")
    except OSError:
        return out
    for tid in tids:
        base = proc / str(pid) / "task" / tid
        stat, comm = _read(base / "stat"), _read(base / "comm")
        if stat is None or comm is None:
            continue
        name = "main" if tid == str(pid) else comm.strip() or "?"
        try:
            out[name] = out.get(name, 0) + parse_stat_cpu(stat)
        except (ValueError, IndexError):
            continue
    return out


def read_footprint(
    pid: int, proc: Path = Path("/proc"), per_thread: bool = True
) -> Snapshot | None:
    """One snapshot of ``pid``; ``None`` when it is gone (or a zombie without memory)."""
    status, stat = _read(proc / str(pid) / "status"), _read(proc / str(pid) / "stat")
    if status is None or stat is None:
        return None
    st = parse_status(status)
    if "VmRSS" not in st:
        return None
    try:
        cpu = parse_stat_cpu(stat)
    except (ValueError, IndexError):
        return None
    return Snapshot(
        t=time.monotonic(),
        rss=st["VmRSS"],
        rss_anon=st.get("RssAnon", 0),
        rss_file=st.get("RssFile", 0) + st.get("RssShmem", 0),
        locked=st.get("VmLck", 0),
        hwm=st.get("VmHWM", st["VmRSS"]),
        threads=st.get("Threads", 0),
        cpu_ticks=cpu,
        thread_ticks=thread_ticks(pid, proc) if per_thread else {},
    )


def role_of(cmdline: list[str]) -> str | None:
    """The rig role of a ``python -m rt_controller.cli ROLE ...`` command line."""
    for i, arg in enumerate(cmdline):
        if arg == "rt_controller.cli" and i + 1 < len(cmdline):
            role = cmdline[i + 1]
            return role if role in ROLES else None
    return None


def children_of(pid: int, proc: Path = Path("/proc")) -> list[int]:
    """Direct children of ``pid`` (all of its threads'), from ``/proc/PID/task/*/children``."""
    out: list[int] = []
    try:
        tids = os.listdir(proc / str(pid) / "task")
    except OSError:
        return out
    for tid in tids:
        text = _read(proc / str(pid) / "task" / tid / "children") or ""
        out += [int(c) for c in text.split()]
    return out


def cpu_percent(first: Snapshot, last: Snapshot, hz: float) -> float | None:
    """CPU use between two snapshots in % of one core."""
    dt = last.t - first.t
    return None if dt <= 0 else 100.0 * (last.cpu_ticks - first.cpu_ticks) / hz / dt


def summarize(series: list[Snapshot], window: tuple[float, float], hz: float) -> dict[str, Any]:
    """The reported figures of one process: peaks over its whole life, CPU over ``window``
    (monotonic seconds; the snapshots closest inside it), per thread name too."""
    inside = [s for s in series if window[0] <= s.t <= window[1]]
    out: dict[str, Any] = {
        "samples": len(series),
        "peak_rss_mb": max(s.rss for s in series) / MIB,
        "peak_rss_anon_mb": max(s.rss_anon for s in series) / MIB,
        "peak_rss_file_mb": max(s.rss_file for s in series) / MIB,
        "peak_locked_mb": max(s.locked for s in series) / MIB,
        "vm_hwm_mb": max(s.hwm for s in series) / MIB,
        "peak_threads": max(s.threads for s in series),
        "cpu_percent": None,
        "cpu_window_s": None,
        "thread_cpu_percent": {},
    }
    if len(inside) >= 2:
        a, b = inside[0], inside[-1]
        dt = b.t - a.t
        out["cpu_percent"] = cpu_percent(a, b, hz)
        out["cpu_window_s"] = dt
        names = set(a.thread_ticks) | set(b.thread_ticks)
        out["thread_cpu_percent"] = {
            n: 100.0 * (b.thread_ticks.get(n, 0) - a.thread_ticks.get(n, 0)) / hz / dt
            for n in sorted(names)
        }
    return out


class FootprintSampler:
    """Samples the rig children of ``parent`` (default: this process) every ``interval_s``.

    A context manager: sampling runs between ``__enter__`` and ``__exit__``. The CPU window of
    :meth:`summary` is the last ``steady_s`` seconds in which the controller was alive (the
    start-up compile and the shutdown are left out); peaks cover the whole run.
    """

    def __init__(self, parent: int | None = None, interval_s: float = 0.2) -> None:
        self.parent = os.getpid() if parent is None else parent
        self.interval_s = interval_s
        self.series: dict[str, list[Snapshot]] = {}
        self._pids: dict[int, str] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="footprint", daemon=True)

    def _role(self, pid: int) -> str | None:
        if pid not in self._pids:
            text = _read(Path("/proc") / str(pid) / "cmdline")
            role = role_of(text.split("\0")) if text else None
            if role is None:
                return None  # not exec'd yet (no or this process's command line): ask again
            self._pids[pid] = role
        return self._pids[pid]

    def sample(self) -> None:
        for pid in children_of(self.parent):
            role = self._role(pid)
            if role is None:
                continue
            self._take(role, pid)
            sub = CHILD_ROLES.get(role)
            if sub is not None:
                for child in children_of(pid):
                    self._take(sub, child)

    def _take(self, role: str, pid: int) -> None:
        snap = read_footprint(pid)
        if snap is not None:
            self.series.setdefault(role, []).append(snap)

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            self.sample()

    def __enter__(self) -> FootprintSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def summary(self, steady_s: float) -> dict[str, Any]:
        """Per role: :func:`summarize` over the controller's last ``steady_s`` seconds."""
        hz = float(os.sysconf("SC_CLK_TCK")) if hasattr(os, "sysconf") else 100.0
        ctl = self.series.get("controller") or []
        end = ctl[-1].t if ctl else max((s[-1].t for s in self.series.values()), default=0.0)
        window = (end - steady_s, end)
        return {role: summarize(s, window, hz) for role, s in sorted(self.series.items())}
