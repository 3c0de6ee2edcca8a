"""The CANopen timing of a ``cia402`` run, from its raw frames (``/hal/can/tx`` as the
controller sent them, ``/hal/can/rx`` as it received them; each stamped by the controller's
monotonic clock when the frame passed its bus, :class:`hal.can_tap.FrameTap`):

- **SYNC jitter**: the controller's SYNC producer, the interval between SYNCs and its error
  against the control period (``|interval - period|``);
- **SYNC to TPDO**: a SYNC sent until the last TPDO answering it (TPDO1 and TPDO2 of every
  drive) was received;
- **PDO round trip**: the last RPDO before a SYNC sent until that SYNC's last TPDO received
  (the torque out, latched at the SYNC, the drives' answer in);
- **torque to effect**: an RPDO with a new target torque sent until the drive's torque actual
  0x6077 reported that value in a TPDO2 (a target replaced before it took effect is counted as
  ``superseded``, one never reported as ``never``);
- the **EMCYs** (time, node, code, text) and the power states the drives reported.

Frames are decoded by :func:`hal.cia402_frames.decode`; ``window`` limits the timing figures
to the ticks of the run (boot and deactivation send SYNCs at their own pace).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hal.cia402_frames import decode
from rt_controller.sample_stats import summary_stats

TIMING_KEYS = ("median", "p99", "max")


@dataclass(frozen=True)
class Frame:
    """One raw frame of the log, decoded."""

    t_ns: int
    direction: str
    cob_id: int
    fields: dict[str, Any]

    @property
    def kind(self) -> str:
        return self.fields["kind"]

    @property
    def node(self) -> int | None:
        return self.fields.get("node")


def decoded_frames(can_rx: Iterable[dict], can_tx: Iterable[dict]) -> list[Frame]:
    """Every raw frame of the log decoded, in time order (a record with bad hex is decoded as
    an empty payload; :func:`decode` marks what does not fit; one without an integer id or
    time stamp is kept as an ``other`` frame with an ``error``, in no figure)."""
    out: list[Frame] = []
    for direction, frames in (("rx", can_rx), ("tx", can_tx)):
        for f in frames:
            try:
                data = bytes.fromhex(f.get("data") or "")
            except (TypeError, ValueError):
                data = b""
            t_ns, cob_id = f.get("t_ns"), f.get("arbitration_id")
            if not all(_number(x) for x in (t_ns, cob_id)):
                broken = {"kind": "other", "node": None, "error": "no integer id or time stamp"}
                out.append(Frame(0, direction, -1, broken))
                continue
            out.append(Frame(int(t_ns), direction, int(cob_id), decode(int(cob_id), data)))
    out.sort(key=lambda fr: fr.t_ns)
    return out


def _number(x: Any) -> bool:
    """A finite JSON number (not a bool, null or text)."""
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _in(window: tuple[int, int] | None, t_ns: int) -> bool:
    return window is None or window[0] <= t_ns <= window[1]


def sync_jitter(
    frames: Sequence[Frame], period_s: float | None, window: tuple[int, int] | None
) -> dict:
    """SYNC intervals (µs) and their error against ``period_s`` (``|interval - period|``);
    with ``period_s`` None (a lockstep run: its SYNCs follow the world's steps, not a clock)
    the error is not computed (every figure None)."""
    sent = [f.t_ns for f in frames if f.kind == "sync" and f.direction == "tx"]
    t = np.array([t for t in sent if _in(window, t)], dtype=float)
    interval = np.diff(t) / 1e3
    return {
        "syncs": int(t.size),
        "interval_us": summary_stats(interval, TIMING_KEYS),
        "period_error_us": (
            dict.fromkeys(TIMING_KEYS)
            if period_s is None
            else summary_stats(np.abs(interval - period_s * 1e6), TIMING_KEYS)
        ),
    }


def sync_to_tpdo(
    frames: Sequence[Frame], nodes: Sequence[int], window: tuple[int, int] | None
) -> dict:
    """Per SYNC in ``window``: until its last TPDO (both TPDOs of every node in ``nodes``)
    received, and from the last RPDO before it; SYNCs not fully answered before the next are
    counted in ``incomplete``."""
    want = {(kind, n) for n in nodes for kind in ("tpdo1", "tpdo2")}
    latency, round_trip = [], []
    incomplete = 0
    sync_ns: int | None = None
    rpdo_ns: int | None = None
    last_rpdo: int | None = None
    seen: dict[tuple[str, int], int] = {}

    def close() -> None:
        nonlocal incomplete
        if sync_ns is None or not _in(window, sync_ns):
            return
        if set(seen) >= want:
            last = max(seen[k] for k in want)
            latency.append((last - sync_ns) / 1e3)
            if rpdo_ns is not None:
                round_trip.append((last - rpdo_ns) / 1e3)
        else:
            incomplete += 1

    for f in frames:
        if f.direction == "tx" and f.kind == "rpdo1":
            last_rpdo = f.t_ns
        elif f.direction == "tx" and f.kind == "sync":
            close()
            sync_ns, rpdo_ns, seen = f.t_ns, last_rpdo, {}
            last_rpdo = None
        elif f.direction == "rx" and f.kind in ("tpdo1", "tpdo2") and "error" not in f.fields:
            seen.setdefault((f.kind, f.node), f.t_ns)
    close()
    return {
        "sync_to_tpdo_us": summary_stats(latency, TIMING_KEYS),
        "pdo_round_trip_us": summary_stats(round_trip, TIMING_KEYS),
        "answered": len(latency),
        "incomplete": incomplete,
    }


def torque_to_effect(frames: Sequence[Frame], window: tuple[int, int] | None) -> dict:
    """Per node: an RPDO whose target torque differs from the node's RPDO before it, sent in
    ``window``, until a TPDO2 of that node reports torque actual equal to it."""
    pending: dict[int, tuple[int, int]] = {}
    last_target: dict[int, int] = {}
    latency: list[float] = []
    superseded = 0
    for f in frames:
        node = f.node
        if node is None or "error" in f.fields:
            continue
        if f.direction == "tx" and f.kind == "rpdo1":
            target = f.fields["target_torque"]
            previous = last_target.get(node, target)  # the first RPDO sets the baseline
            if target != previous and _in(window, f.t_ns):
                superseded += int(node in pending)
                pending[node] = (f.t_ns, target)
            last_target[node] = target
        elif f.direction == "rx" and f.kind == "tpdo2" and node in pending:
            sent_ns, target = pending[node]
            if f.fields["torque_actual"] == target:
                latency.append((f.t_ns - sent_ns) / 1e3)
                del pending[node]
    return {
        "torque_to_effect_us": summary_stats(latency, TIMING_KEYS),
        "changes": len(latency),
        "superseded": superseded,
        "never": len(pending),
    }


def emcys(frames: Sequence[Frame], t0_ns: int | None = None) -> list[dict[str, Any]]:
    """Every EMCY received: time (s from ``t0_ns``, else ns), node, code (hex), its text and
    whether it is an *error reset* (code 0x00xx: a drive left FAULT)."""
    out = []
    for f in frames:
        if f.kind != "emcy" or f.direction != "rx" or "error" in f.fields:
            continue
        out.append(
            {
                "t_s": None if t0_ns is None else (f.t_ns - t0_ns) / 1e9,
                "t_ns": f.t_ns,
                "node": f.node,
                "code": f"0x{f.fields['code']:04X}",
                "text": f.fields["text"],
                "error_reset": f.fields["error_reset"],
            }
        )
    return out


def drive_states(frames: Sequence[Frame]) -> dict[str, list[str]]:
    """Per node, the power states its TPDO1s reported, each change once, in order."""
    out: dict[str, list[str]] = {}
    for f in frames:
        if f.kind == "tpdo1" and f.direction == "rx" and "state" in f.fields:
            states = out.setdefault(str(f.node), [])
            if not states or states[-1] != f.fields["state"]:
                states.append(f.fields["state"])
    return out


def canopen_timing(
    can_rx: Iterable[dict],
    can_tx: Iterable[dict],
    *,
    period_s: float | None,
    nodes: Sequence[int],
    window: tuple[int, int] | None = None,
    t0_ns: int | None = None,
) -> dict[str, Any] | None:
    """The CANopen figures of one run (see the module docstring); None when its frames hold
    no SYNC (not a cia402 log, or one recorded without raw frames)."""
    frames = decoded_frames(can_rx, can_tx)
    if not any(f.kind == "sync" and f.direction == "tx" for f in frames):
        return None
    counts: dict[str, int] = {}
    for f in frames:
        counts[f.kind] = counts.get(f.kind, 0) + 1
    return {
        "frames": len(frames),
        "kinds": counts,
        "undecodable": sum("error" in f.fields for f in frames),
        "sync": sync_jitter(frames, period_s, window),
        **sync_to_tpdo(frames, nodes, window),
        **torque_to_effect(frames, window),
        "emcys": emcys(frames, t0_ns),
        "drive_states": drive_states(frames),
    }


def log_timing(log: Any) -> dict[str, Any] | None:
    """:func:`canopen_timing` of a :class:`~rt_controller.logtools.reader.LoadedLog`: the
    period and node ids from its configuration, times from the first tick, and the window
    from the first tick's start to the end of its last tick's write. The arming's SYNCs
    precede the window; a lockstep tick's SYNC falls between the tick before and its own
    start (period 0's is the arming's last), a realtime tick sends its SYNC at its write;
    deactivation's come after. A lockstep log's SYNCs are paced by the world, not the period:
    no SYNC period error. None for a log without CANopen frames."""
    cfg = log.config
    if cfg is None or cfg.hardware.profile != "cia402" or not (log.can_rx or log.can_tx):
        return None
    t = log.cycles.get("t_ns")
    period_ns = round(1e9 / cfg.rates.control_hz)
    window = None
    t0 = None
    if t is not None and t.size:
        t0 = int(t[0])
        cycle_us = log.cycles.get("cycle_us")
        write_ns = int(cycle_us[-1] * 1e3) + 1_000 if cycle_us is not None else period_ns
        window = (t0, int(t[-1]) + write_ns)
    clock = (getattr(log, "run_info", None) or {}).get("clock") or cfg.controller.clock
    return canopen_timing(
        log.can_rx,
        log.can_tx,
        period_s=None if clock == "lockstep" else period_ns / 1e9,
        nodes=(cfg.cia402.node_id_1, cfg.cia402.node_id_2),
        window=window,
        t0_ns=t0,
    )


__all__ = [
    "Frame",
    "canopen_timing",
    "decoded_frames",
    "drive_states",
    "emcys",
    "log_timing",
    "sync_jitter",
    "sync_to_tpdo",
    "torque_to_effect",
]
