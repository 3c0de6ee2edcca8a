"""Benchmark of the compiled per-tick rule (``hil bench solver``'s ``decide`` figures).

The whole decide phase as the daemon runs it, one compiled call
(:mod:`rt_controller.control.decide_kernel`): prediction, law with its C/GMRES update and
fallback, eq. (11) and saturation, l and V. Timed with ``time.perf_counter_ns`` around the
call alone (what the cycle record's ``law_us`` holds), in three ways:

* ``closed_loop``: the paper scenario with the plant stepped between calls (as
  :mod:`rt_controller.rig.bench_solver` runs the update), in episodes that start with a cold
  law;
* ``warm``: recorded ticks replayed back to back (caches hot);
* ``paced``: recorded ticks replayed once per control period, the core asleep in between,
  as the live daemon leaves it.

``paced_floor`` is what a call costs on this core before it computes anything, timed the same
way once per period: an empty Python call between the two clock reads (``python_call``) and a
compiled function that does nothing, entered with the rule's arguments bound as the rule's own
call is (``compiled_entry``). On a core that has idled a period, these take tens of
microseconds where they take one or two when warm: the part of ``paced`` no kernel work removes.

It also reports what the call touches: the executable bytes of its compiled object (numba's
cache entry for this CPU) and the bytes of the arrays it reads and writes (``working_set``).
"""

from __future__ import annotations

import functools
import gc
import struct
import time
from typing import Any

import numpy as np
from numba import njit

from hal.config import RigConfig
from rt_controller.control import decide_kernel as dk
from rt_controller.control.controller import Controller
from rt_controller.control.state import IO
from rt_controller.sample_stats import summary_stats

SNAPSHOTS = 200
"""Ticks recorded (evenly spread over the closed loop) for the warm and paced replays."""
_SHF_EXECINSTR = 0x4


def executable_bytes(elf: bytes) -> int:
    """Total size of the executable sections of an ELF64 little-endian object."""
    shoff = struct.unpack_from("<Q", elf, 0x28)[0]
    shentsize, shnum = struct.unpack_from("<HH", elf, 0x3A)
    total = 0
    for i in range(shnum):
        base = shoff + i * shentsize
        flags = struct.unpack_from("<Q", elf, base + 8)[0]
        size = struct.unpack_from("<Q", elf, base + 32)[0]
        if flags & _SHF_EXECINSTR:
            total += size
    return total


def _elf_objects(obj: Any, depth: int = 0):
    if isinstance(obj, bytes | bytearray) and obj[:4] == b"\x7fELF":
        yield bytes(obj)
    elif isinstance(obj, tuple | list) and depth < 8:
        for x in obj:
            yield from _elf_objects(x, depth + 1)


def code_size(dispatcher: Any) -> dict[str, int] | None:
    """Bytes of the compiled object of ``dispatcher`` for this CPU, from numba's cache (with
    everything linked into it: the kernels it calls and their runtime); ``None`` if uncached."""
    from numba.core.registry import cpu_target

    cache = getattr(dispatcher, "_cache", None)
    if cache is None or not hasattr(cache, "_cache_file"):
        return None
    magic = cpu_target.target_context.codegen().magic_tuple()
    cache_file = cache._cache_file
    for (_sig, key_magic, _stamp), name in cache_file._load_index().items():
        if key_magic != magic:
            continue
        for elf in _elf_objects(cache_file._load_data(name)):
            return {"object_bytes": len(elf), "code_bytes": executable_bytes(elf)}
    return None


def working_set(rule: dk.CompiledRule) -> dict[str, int]:
    """Bytes of the arrays one call reads and writes."""
    arrays = {
        "io": rule.io,
        "model": rule.p,
        "limits": rule.lim,
        "history": rule.hist_t,
        "history_tau": rule.hist_tau,
        "rule_state": rule.ks,
        "solver_params": rule.P,
        "solver_int_params": rule.iP,
        "solver_state": rule.st,
        "solver_work": rule.work,
    }
    out = {k: int(a.nbytes) for k, a in arrays.items()}
    out["total"] = sum(out.values())
    return out


def _state(rule: dk.CompiledRule) -> tuple[np.ndarray, ...]:
    return (rule.io.copy(), rule.ks.copy(), rule.st.copy(), rule.hist_t.copy(),
            rule.hist_tau.copy())  # fmt: skip


def _restore(rule: dk.CompiledRule, snap: tuple[np.ndarray, ...]) -> None:
    for dst, src in zip((rule.io, rule.ks, rule.st, rule.hist_t, rule.hist_tau), snap, strict=True):
        dst[...] = src


@njit(cache=True)
def _noop(io, p, lim, hist_t, hist_tau, ks, P, iP, st, work):
    """The rule's signature, no work: the entry cost alone."""


def _nothing() -> None:
    """An empty Python call."""


def paced_floor(rule: dk.CompiledRule, period_s: float, calls: int) -> dict[str, Any]:
    """Median and p99 (µs) of an empty Python call and of a no-op compiled call with the rule's
    arguments bound, each timed once per ``period_s`` (see the module docstring)."""
    from rt_controller.control.rhc.solver import compiled_entry

    args = rule.arguments
    _noop(*args)
    cases = {
        "python_call": _nothing,
        "compiled_entry": functools.partial(compiled_entry(_noop, *args), *args),
    }
    out: dict[str, Any] = {"period_s": period_s}
    for name, fn in cases.items():
        fn()
        ns = np.zeros(calls, dtype=np.int64)
        for i in range(calls):
            time.sleep(period_s)
            start = time.perf_counter_ns()
            fn()
            ns[i] = time.perf_counter_ns() - start
        out[name] = summary_stats(ns / 1e3)
    return out


def _timed(rule: dk.CompiledRule) -> int:
    call = rule.call  # as Controller.decide makes it
    start = time.perf_counter_ns()
    call()
    return time.perf_counter_ns() - start


def bench_decide(cfg: RigConfig, updates: int, plant_step: Any, episode_s: float) -> dict[str, Any]:
    """The ``decide`` figures for ``cfg`` (its law: run ``rhc`` for the C/GMRES figures), the
    scenario restarting every ``episode_s`` seconds with a cold law."""
    ctl = Controller(cfg)
    ctl.warm_up()
    rule = ctl.rule
    assert rule is not None
    s, period = cfg.scenario, 1.0 / cfg.rates.control_hz
    episode = max(1, round(episode_s * cfg.rates.control_hz))
    every = max(1, updates // SNAPSHOTS)
    ns = np.zeros(updates, dtype=np.int64)
    first = np.zeros(updates, dtype=bool)
    snaps: list[tuple[np.ndarray, ...]] = []
    io = rule.io
    q = dq = f = np.zeros(2)
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        for k in range(updates):
            if k % episode == 0:
                q, dq, f = (np.array(v, dtype=float) for v in (s.q0, s.dq0, s.f0))
                ctl.reset()
                first[k] = True
            t = (k % episode) * period
            io[IO.T], io[IO.NOW] = t, t
            io[IO.Q : IO.Q + 2], io[IO.DQ : IO.DQ + 2] = q, dq
            io[IO.F : IO.F + 2] = f
            io[IO.STATE_AGE : IO.ENABLED] = 0.0
            io[IO.ENABLED] = 1.0
            if k % every == 0 and not first[k]:
                snaps.append(_state(rule))
            ns[k] = _timed(rule)
            q, dq, f = plant_step(q, dq, f, io[IO.U : IO.U + 2].copy())
        warm = np.zeros(len(snaps), dtype=np.int64)
        for i, snap in enumerate(snaps):
            _restore(rule, snap)
            _timed(rule)
            _restore(rule, snap)
            warm[i] = _timed(rule)
        paced = np.zeros(len(snaps), dtype=np.int64)
        for i, snap in enumerate(snaps):
            _restore(rule, snap)
            time.sleep(period)
            paced[i] = _timed(rule)
        floor = paced_floor(rule, period, len(snaps))
    finally:
        if gc_was_enabled:
            gc.enable()
        ctl.reset()
    return {
        "law": cfg.controller.law,
        "closed_loop_us": summary_stats(ns[~first] / 1e3),
        "first_tick_us": summary_stats(ns[first] / 1e3),
        "warm_us": summary_stats(warm / 1e3),
        "paced_us": {**summary_stats(paced / 1e3), "period_s": period},
        "paced_floor_us": floor,
        "code": code_size(dk.decide_tick),
        "working_set_bytes": working_set(rule),
    }
