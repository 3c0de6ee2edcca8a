"""Best-effort real-time process settings; each refusal becomes a warning, never an error.

Memory locking: after warm-up, lock the pages this process has touched so far (the *present*
bit of ``/proc/self/pagemap``), leaving out mappings the loop never runs (:data:`COLD_MAPPINGS`:
the LLVM compiler behind numba; the compiled code itself lives in anonymous memory and is
locked). Nothing is locked in advance: thread stacks, malloc arena reserves and the untouched
parts of libraries stay unlocked and non-resident; pages the loop first touches later are
ordinary (minor) faults, which is why the warm-up runs every branch. ``mlockall(MCL_FUTURE)``
would instead lock about 1.1 GB for a daemon that needs about 100 MB.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import mmap
import os
import struct
import threading
from dataclasses import dataclass, field

PR_SET_TIMERSLACK = 29
M_ARENA_MAX = -8
COLD_MAPPINGS = ("libllvmlite",)
"""Mappings (by file name part) never locked: code the loop does not run after warm-up."""
THREAD_STACK_BYTES = 512 * 1024
"""Stack of the Python threads of the rig's processes (zenoh callbacks, the vision and
emulator loops): they recurse a few frames deep; the 8 MB default only grows the address
space."""
_PAGEMAP_PRESENT = 1 << 63


@dataclass
class RtReport:
    """What was applied and what was refused (with the reason)."""

    applied: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name or "libc.so.6", use_errno=True)
    except OSError:
        return None


def lean_process(arena_max: int = 2, stack_bytes: int = THREAD_STACK_BYTES) -> RtReport:
    """Before any thread starts: small Python thread stacks and at most ``arena_max`` malloc
    arenas (glibc gives every thread that allocates an arena of its own, up to 8 per core)."""
    rep = RtReport()
    try:
        threading.stack_size(stack_bytes)
        rep.applied.append(f"thread stacks {stack_bytes // 1024} KiB")
    except (ValueError, RuntimeError) as exc:
        rep.warnings.append(f"thread stack size refused ({exc})")
    libc = _libc()
    if libc is not None and hasattr(libc, "mallopt") and arena_max > 0:
        if libc.mallopt(M_ARENA_MAX, arena_max) == 1:
            rep.applied.append(f"malloc arenas <= {arena_max}")
        else:
            rep.warnings.append("mallopt(M_ARENA_MAX) refused")
    return rep


def lockable(perms: str, path: str) -> bool:
    """Whether a mapping may be locked by ``"touched"``: accessible, not a kernel page, not cold."""
    if perms.startswith("---") or path in ("[vsyscall]", "[vvar]", "[vdso]"):
        return False
    return not any(cold in path for cold in COLD_MAPPINGS)


def present_runs(pagemap: bytes, start: int, page: int) -> list[tuple[int, int]]:
    """Contiguous runs (address, length) of pages whose pagemap entry has the present bit."""
    runs: list[tuple[int, int]] = []
    n = len(pagemap) // 8
    run_start = None
    for i, e in enumerate((*struct.unpack(f"<{n}Q", pagemap[: n * 8]), 0)):  # 0: the end
        if e & _PAGEMAP_PRESENT:
            if run_start is None:
                run_start = i
        elif run_start is not None:
            runs.append((start + run_start * page, (i - run_start) * page))
            run_start = None
    return runs


def _lock(libc: ctypes.CDLL, rep: RtReport) -> None:
    """mlock the present pages of every lockable mapping (see the module docstring)."""
    page, locked, refused = mmap.PAGESIZE, 0, 0
    libc.mlock.argtypes = (ctypes.c_void_p, ctypes.c_size_t)
    try:
        with open("/proc/self/maps") as f:
            maps = [line.split(maxsplit=5) for line in f.read().splitlines()]
        with open("/proc/self/pagemap", "rb", buffering=0) as pm:
            for parts in maps:  # start-end perms offset dev inode [path]
                path = parts[5].strip() if len(parts) == 6 else ""
                if len(parts) < 5 or not lockable(parts[1], path):
                    continue
                lo, hi = (int(x, 16) for x in parts[0].split("-"))
                pm.seek(lo // page * 8)
                for addr, size in present_runs(pm.read((hi - lo) // page * 8), lo, page):
                    if libc.mlock(addr, size) == 0:
                        locked += size
                    else:
                        refused += size
    except OSError as exc:
        rep.warnings.append(f"locking touched pages failed ({exc})")
        return
    if locked:
        rep.applied.append(f"mlock {locked / 2**20:.0f} MB touched")
    if refused:
        err = os.strerror(ctypes.get_errno())
        rep.warnings.append(f"mlock refused for {refused / 2**20:.0f} MB ({err})")


def apply_realtime(priority: int = 80, cpu: int = -1, lock_memory: bool = True) -> RtReport:
    """SCHED_FIFO, CPU affinity, locking the touched pages (see the module docstring), 1 ns
    timer slack and a frozen GC heap. Call it after warm-up: what has been touched by then is
    what gets locked."""
    rep = RtReport()
    gc.collect()
    gc.freeze()
    rep.applied.append("GC heap frozen")
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        rep.applied.append(f"SCHED_FIFO priority {priority}")
    except (OSError, AttributeError) as exc:
        rep.warnings.append(f"SCHED_FIFO refused ({exc}); running with normal scheduling")
    if cpu >= 0:
        try:
            os.sched_setaffinity(0, {cpu})
            rep.applied.append(f"pinned to CPU {cpu}")
        except (OSError, ValueError) as exc:
            rep.warnings.append(f"CPU affinity {cpu} refused ({exc})")
    libc = _libc()
    if libc is None:
        rep.warnings.append("libc not found: no memory locking, no timer slack")
    else:
        if lock_memory:
            _lock(libc, rep)
        if libc.prctl(PR_SET_TIMERSLACK, 1, 0, 0, 0) == 0:
            rep.applied.append("timer slack 1 ns")
        else:
            rep.warnings.append(f"timer slack refused ({os.strerror(ctypes.get_errno())})")
    return rep


class GcPaused:
    """Context manager: the cyclic GC is off inside the loop and restored afterwards."""

    def __enter__(self) -> GcPaused:
        self._was = gc.isenabled()
        gc.disable()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._was:
            gc.enable()
