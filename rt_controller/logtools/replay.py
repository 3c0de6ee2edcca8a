"""Offline replay of a controller log: re-run the law on the recorded inputs, compare the outputs.

This is the regression tool behind ``hil replay``: a fresh
:class:`~rt_controller.control.controller.Controller` built from the log's ``hil.config``
metadata (or an override, e.g. a changed gain or solver setting) is fed, tick by tick, exactly
what the daemon fed its own controller — ``sim_time_s`` (the t the law was called with),
``q``, ``dq``, ``f``, ``f_stale`` and ``state_stale`` as received — through the same per-tick rule,
:meth:`Controller.decide`, after the daemon's warm-up. Its ``u`` and ``tau`` are compared with
the recorded ones: JSON floats round-trip float64 exactly, so an unchanged controller reproduces
a log bit for bit and any difference is a change in the code or the settings.

Comparison rules: a value recorded as ``null`` reads back as NaN; NaN against NaN is equal, NaN
against a number is an infinite difference. A ``no_state`` tick (zero torque) compares as
equal when the replay also has no state. Missing optional fields are derived: ``f_stale`` from
a non-finite ``f``, ``state_stale`` from ``law == "no_state"`` or a non-finite ``q``,
``sim_time_s`` from ``tick / rate`` (each noted). A truncated log replays as far as its
complete chunks go, with a note; cycle records missing from the middle of a log (recorder
drops) are noted, since a law with memory (RHC) may diverge after them.

``out=`` writes the replayed run as a new MCAP log (:class:`CycleRecorder`, same configuration,
``hil.run`` noting the source log under ``replay_of`` and the source's run info under
``source.*``). Each cycle record is the recorded one with the replay's ``u``, ``tau``, ``xi``,
``law``, ``residual``, ``iterations``, ``fallback``, ``tau_saturated``, ``cost`` and ``V``;
``tick``, ``t_ns``, ``sim_time_s``, the inputs, their ages and ``missed_periods`` are kept as
recorded, and the loop-timing fields (``lateness_us``, ``read_us``, ``solve_us``, ``write_us``,
``cycle_us``, ``e2e_us``; those the source has) are zero with ``deadline_miss`` false — an
offline replay has no loop timing.
The recorded raw inputs (``/hal/can/rx``, ``/vision/features``) are copied when the log was read
with them, so the new log can itself be replayed or republished.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hal.config import RigConfig
from hal.drive_state import MODE_ENABLED, MODES
from rt_controller.calibration.parameters import LAW_KEYS, accepted_changes, judge
from rt_controller.control.controller import Controller
from rt_controller.errors import LogError
from rt_controller.logtools.reader import LoadedLog, read_log, same_file
from rt_controller.logtools.replay_out import cycle_record_at, inherited_loss, out_log
from rt_controller.runtime.cycle_record import TIMING_FIELDS, decision_fields
from rt_controller.runtime.recorder import CYCLE_TOPIC


@dataclass
class ReplayResult:
    """Outcome of :func:`replay_log`: how far the replay's outputs are from the recorded ones."""

    path: Path
    law: str
    ticks: int
    tol: float
    max_abs_du: float = 0.0
    max_abs_dtau: float = 0.0
    worst_tick: int | None = None
    """Tick with the largest difference of u or tau (None when every tick matches exactly)."""
    worst_tick_du: int | None = None
    worst_tick_dtau: int | None = None
    ticks_over_tol: int = 0
    law_mismatches: int = 0
    """Ticks whose mode/law name (``ioc``, ``hold``, ``no_state``...) differs from the log's."""
    truncated: bool = False
    """The log ends early or is damaged: only the ticks before the damage were replayed."""
    skipped_records: int = 0
    """``/controller/cycle`` records the log holds but that could not be read (not JSON objects,
    or without a tick): their ticks were not replayed, so the log is damaged."""
    allow_partial: bool = False
    """Accept a truncated log as a successful replay of what it holds."""
    notes: list[str] = field(default_factory=list)
    out: Path | None = None
    u: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    """Replayed u, one row per tick."""
    tau: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    """Replayed tau, one row per tick."""
    compile_target: str = ""
    """Which numba compile target the replay ran on, and why (one line; see
    :mod:`rt_controller.logtools.target_replay`)."""
    cross_target_spread: float | None = None
    """The largest |difference| of u or tau between replays of this log compiled for two
    targets (measured when the recorded target cannot run here and the replay is over tol)."""
    spread_limit: float | None = None
    """The largest |difference| from the log the cross-target spread explains."""

    @property
    def matches(self) -> bool:
        """Every replayed tick within ``tol`` for both u and tau."""
        return self.ticks_over_tol == 0

    @property
    def within_spread(self) -> bool | None:
        """A replay over ``tol`` on another compile target than the log's: whether the
        difference is within what the measured cross-target spread explains. None when no
        spread was measured (the log's own target ran, or the replay was within ``tol``)."""
        if self.spread_limit is None:
            return None
        return max(self.max_abs_du, self.max_abs_dtau) <= self.spread_limit

    @property
    def partial(self) -> bool:
        """Not every tick of the log was replayed: it is truncated, or records were skipped."""
        return self.truncated or self.skipped_records > 0

    @property
    def ok(self) -> bool:
        """Every tick matches (or differs by no more than the cross-target spread), and the
        log was whole (or a partial one was allowed)."""
        same = self.matches or bool(self.within_spread)
        return same and (not self.partial or self.allow_partial)

    def as_dict(self) -> dict[str, Any]:
        """The JSON object of ``hil replay --json`` (non-finite values as None)."""

        def num(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None

        out: dict[str, Any] = {
            "log": str(self.path),
            "law": self.law,
            "ticks": self.ticks,
            "max_abs_du": num(self.max_abs_du),
            "max_abs_dtau": num(self.max_abs_dtau),
            "worst_tick": self.worst_tick,
            "worst_tick_du": self.worst_tick_du,
            "worst_tick_dtau": self.worst_tick_dtau,
            "ticks_over_tol": self.ticks_over_tol,
            "law_mismatches": self.law_mismatches,
            "tol": self.tol,
            "ok": self.ok,
            "matches": self.matches,
            "truncated": self.truncated,
            "skipped_records": self.skipped_records,
            "allow_partial": self.allow_partial,
            "compile_target": self.compile_target,
            "cross_target_spread": self.cross_target_spread,
            "within_spread": self.within_spread,
            "notes": list(self.notes),
        }
        if self.out is not None:
            out["out"] = str(self.out)
        return out

    def failure_line(self) -> str:
        """One line saying why the replay failed (for a non-zero exit)."""
        if not (self.matches or self.within_spread):
            return f"replay differs from the log: {self.difference()}{self._why()}"
        skipped = f"{self.skipped_records} cycle record(s) could not be read and were skipped"
        if not self.truncated:
            what = f"{skipped}, {self.ticks} ticks replayed"
        else:
            first = self.notes[0] if self.notes else "the log ends early"
            what = f"only the {self.ticks} ticks it holds were replayed ({first})"
            what += f"; {skipped}" if self.skipped_records else ""
        return (
            f"log is incomplete or damaged: {what}; pass --allow-partial to accept a partial replay"
        )

    def difference(self) -> str:
        """The largest differences of tau and u, where, and how many ticks are over tol."""
        return (
            f"max |dtau| = {self.max_abs_dtau:.6g} at tick {self.worst_tick_dtau} (tol "
            f"{self.tol:g}); max |du| = {self.max_abs_du:.6g} at tick {self.worst_tick_du}; "
            f"{self.ticks_over_tol} of {self.ticks} ticks over tol"
        )

    def _why(self) -> str:
        """What the difference is measured against: the compile target and its spread."""
        if self.spread_limit is not None:
            return (
                f"; more than the cross-target spread explains (up to {self.spread_limit:.3g}; "
                f"{self.compile_target}): a change in the code, the settings or the inputs"
            )
        if self.compile_target:
            return f"; {self.compile_target}"
        return ""


def abs_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Element-wise |a - b| where NaN equals NaN and NaN against a number is +inf."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    na, nb = np.isnan(a), np.isnan(b)
    with np.errstate(invalid="ignore"):
        d = np.abs(a - b)
    d[na & nb] = 0.0
    d[na ^ nb] = np.inf
    d[np.isnan(d)] = np.inf  # inf - inf of the same sign
    return d


def _bool_column(log: LoadedLog, name: str, default: np.ndarray) -> tuple[np.ndarray, bool]:
    """A bool column with ``default`` where it was not recorded; also whether any was missing."""
    col = log.column(name)
    if col is None:
        return default, True
    if col.dtype == bool:
        return col, False
    values = np.asarray(col, dtype=float)
    missing = np.isnan(values)
    return np.where(missing, default, values != 0.0), bool(missing.any())


def _vec(log: LoadedLog, name: str) -> np.ndarray:
    """A recorded 2-vector field as an (n, 2) float array; LogError when it is not one."""
    col = log.column(name)
    if col is None or col.ndim != 2 or col.shape[1] < 2:
        raise LogError(f"{log.path}: cycle field {name!r} is missing or not a 2-vector")
    return np.asarray(col[:, :2], dtype=float)


def _ms_column(log: LoadedLog, name: str) -> np.ndarray:
    """A per-tick age in ms the daemon compensated; 0 where missing (logs before it did)."""
    col = log.column(name)
    col = np.zeros(log.n_cycles) if col is None else np.asarray(col, dtype=float)
    return np.where(np.isfinite(col), col, 0.0)


def _inputs(log: LoadedLog, cfg: RigConfig, notes: list[str]) -> dict[str, np.ndarray]:
    """Per-tick inputs of :meth:`Controller.decide`; derived optional fields go to ``notes``."""
    n = log.n_cycles
    q, dq, f = _vec(log, "q"), _vec(log, "dq"), _vec(log, "f")
    ticks = np.asarray(log.cycles["tick"], dtype=float)
    law = log.column("law")
    laws = np.array(["" if v is None else str(v) for v in law]) if law is not None else None
    no_state = (laws == "no_state") if laws is not None else np.zeros(n, dtype=bool)
    f_stale, miss_f = _bool_column(log, "f_stale", ~np.all(np.isfinite(f), axis=1))
    state_stale, miss_s = _bool_column(
        log, "state_stale", no_state | ~np.all(np.isfinite(q), axis=1)
    )
    t = log.column("sim_time_s")
    t = np.full(n, np.nan) if t is None else np.asarray(t, dtype=float)
    guess_t = ~np.isfinite(t)
    t = np.where(guess_t, ticks * cfg.rates.control_period_ns / 1e9, t)
    for missing, what in (
        (miss_f, "f_stale (taken as: f not finite)"),
        (miss_s, "state_stale (taken as: law no_state or q not finite)"),
        (bool(guess_t.any()), "sim_time_s (taken as: tick / rate)"),
    ):
        if missing:
            notes.append(f"some cycle records lack {what}")
    predict, f_predict = (_ms_column(log, k) for k in ("predict_ms", "f_predict_ms"))
    late = log.column("lateness_us")  # the daemon's now_s: the release plus the lateness
    late = np.zeros(n) if late is None else np.asarray(late, dtype=float)
    now = t + np.where(np.isfinite(late), late, 0.0) / 1e6
    return {
        "t": t,
        "q": q,
        "dq": dq,
        "f": f,
        "f_stale": f_stale,
        "state_stale": state_stale,
        "predict_s": predict / 1e3,
        "f_predict_s": f_predict / 1e3,
        "now_s": now,
    }


def _gap_note(log: LoadedLog) -> str | None:
    """A note when cycle records are missing between ticks (not explained by missed periods)."""
    ticks = np.asarray(log.cycles["tick"], dtype=float)
    if len(ticks) < 2:
        return None
    missed = log.column("missed_periods")
    missed = np.zeros(len(ticks)) if missed is None else np.nan_to_num(missed.astype(float))
    lost = np.diff(ticks) - 1 - missed[1:]
    n = int(np.sum(lost[lost > 0]))
    dropped = log.recorder_info.get("dropped", "0")
    if n == 0 and dropped in ("", "0"):
        return None
    skipped = log.rejected.get(CYCLE_TOPIC, 0)
    unread = f", {skipped} unreadable in the log" if skipped else ""
    return (
        f"{n} cycle record(s) missing between ticks (recorder dropped {dropped or '?'}{unread}): "
        "a law with memory (rhc) may differ after them"
    )


class _ParameterChanges:
    """The log's accepted online changes (``/controller/parameters``), applied at their ticks
    as the loop applied them: before the tick's rule (:meth:`Controller.reconfigure`)."""

    def __init__(self, log: LoadedLog, cfg: RigConfig) -> None:
        self.pending = accepted_changes(log.parameters)
        self.ticks = log.column("tick")
        self.cfg = cfg

    def apply(self, ctl: Controller, i: int) -> None:
        tick = i if self.ticks is None else int(self.ticks[i])
        while self.pending and self.pending[0][0] <= tick:
            _, changes = self.pending.pop(0)
            self.cfg = judge(self.cfg, changes)
            ctl.reconfigure(self.cfg, law_changed=bool(set(changes) & LAW_KEYS))


DISABLED_MODES = frozenset(MODES) - {MODE_ENABLED}
"""Modes in which the daemon does not run the law (recorded as the tick's ``law``)."""


def _drive_mode(recorded_law: np.ndarray | None, i: int) -> str:
    """The DSP's drive mode at tick ``i`` as the daemon recorded it in the ``law`` field (a
    tick without an enabled DSP is recorded under its mode's name)."""
    if recorded_law is None:
        return MODE_ENABLED
    law = recorded_law[i]
    return law if law in DISABLED_MODES else MODE_ENABLED


def replay_loaded(
    log: LoadedLog,
    *,
    cfg_override: RigConfig | None = None,
    tol: float = 1e-9,
    out: Path | None = None,
    allow_partial: bool = False,
) -> ReplayResult:
    """:func:`replay_log` on a log already read with
    :func:`~rt_controller.logtools.reader.read_log`."""
    if not tol >= 0:
        raise LogError(f"tolerance must be non-negative, got {tol}")
    cfg = cfg_override or log.config
    if cfg is None:
        why = "; ".join(log.notes) or "no hil.config metadata"
        raise LogError(f"{log.path}: the run configuration is unknown ({why}); pass --config")
    n, skipped = log.n_cycles, log.rejected.get(CYCLE_TOPIC, 0)
    if n == 0:
        why = f" ({skipped} unreadable, skipped)" if skipped else ""
        why += f" ({log.notes[0]})" if log.truncated and log.notes else ""
        raise LogError(f"{log.path}: no /controller/cycle records{why}, nothing to replay")
    if out is not None and same_file(out, log.path):
        raise LogError(f"--out {out} would overwrite the log being replayed")
    notes = list(log.notes)
    lost = inherited_loss(log)
    if lost:
        notes.append(lost)
    walk = log.walk
    all_data = walk is not None and walk.data_end and not walk.skipped
    if log.truncated and all_data:
        notes.append(
            "the log is cut in its summary section, after all its data: every tick was "
            "replayed (`hil recover` makes a copy that stock MCAP tools open)"
        )
    truncated = (log.truncated and not all_data) or lost is not None
    if truncated:
        notes.append(f"truncated log: replayed the {n} ticks it holds")
    inputs = _inputs(log, cfg, notes)
    recorded_u, recorded_tau = _vec(log, "u"), _vec(log, "tau")
    gap = _gap_note(log)
    if gap:
        notes.append(gap)
    ctl = Controller(cfg)
    ctl.warm_up()  # as the daemon does before its first tick
    changes = _ParameterChanges(log, cfg)
    recorded_law = log.column("law")
    u = np.zeros((n, 2))
    tau = np.zeros((n, 2))
    laws: list[str] = []
    writing = out_log(Path(out), cfg, log, tol) if out is not None else contextlib.nullcontext()
    with writing as writer:  # renamed onto --out only when whole; on failure nothing is left
        for i in range(n):
            changes.apply(ctl, i)
            d = ctl.decide(
                float(inputs["t"][i]),
                inputs["q"][i],
                inputs["dq"][i],
                inputs["f"][i],
                f_stale=bool(inputs["f_stale"][i]),
                state_stale=bool(inputs["state_stale"][i]),
                drive_mode=_drive_mode(recorded_law, i),
                state_age_s=float(inputs["predict_s"][i]),
                feature_age_s=float(inputs["f_predict_s"][i]),
                now_s=float(inputs["now_s"][i]),
            )
            fields = decision_fields(ctl, d)
            u[i], tau[i] = fields["u"], fields["tau"]
            laws.append(fields["law"])
            if writer is not None:
                record = cycle_record_at(log, i)
                record.update(fields)
                record.update({k: 0.0 for k in TIMING_FIELDS if k in record})
                record["deadline_miss"] = False
                writer.cycle(record)
        if writer is not None:
            writer.raw_inputs(log)
    result = _compare(log, cfg, u, tau, recorded_u, recorded_tau, tol)
    result.allow_partial = allow_partial
    result.truncated = truncated
    result.skipped_records = skipped
    if recorded_law is not None and recorded_law.dtype == object:
        result.law_mismatches = sum(
            str(a) != b for a, b in zip(recorded_law, laws, strict=True) if a is not None
        )
    result.notes = notes
    result.out = None if out is None else Path(out)
    return result


def _compare(
    log: LoadedLog,
    cfg: RigConfig,
    u: np.ndarray,
    tau: np.ndarray,
    recorded_u: np.ndarray,
    recorded_tau: np.ndarray,
    tol: float,
) -> ReplayResult:
    du = abs_diff(u, recorded_u).max(axis=1)
    dtau = abs_diff(tau, recorded_tau).max(axis=1)
    worst = np.maximum(du, dtau)
    ticks = np.asarray(log.cycles["tick"])
    res = ReplayResult(
        path=log.path,
        law=cfg.controller.law,
        ticks=len(ticks),
        tol=tol,
        truncated=log.truncated,
        u=u,
        tau=tau,
    )
    res.max_abs_du, res.max_abs_dtau = float(du.max()), float(dtau.max())

    def where(d: np.ndarray) -> int | None:
        return int(ticks[int(np.argmax(d))]) if d.max() > 0 else None

    res.worst_tick_du, res.worst_tick_dtau, res.worst_tick = where(du), where(dtau), where(worst)
    res.ticks_over_tol = int(np.sum(worst > tol))
    return res


def replay_log(
    path: str | Path,
    *,
    cfg_override: RigConfig | None = None,
    tol: float = 1e-9,
    out: Path | None = None,
    allow_partial: bool = False,
) -> ReplayResult:
    """Re-run a fresh controller on the inputs recorded in ``path`` and compare u and tau.

    ``cfg_override`` replaces the log's configuration (e.g. a changed gain); ``tol`` is the
    largest absolute difference of any component of u or tau that still counts as equal;
    ``out`` writes the replayed run as a new MCAP log (see the module docstring). Raises
    :class:`~rt_controller.errors.LogError` for a missing/non-MCAP file, a log without
    configuration (and no override) or without cycles. A truncated or damaged log replays as
    far as it goes; it counts as ``ok`` only with ``allow_partial``.
    """
    log = read_log(path, raw=out is not None)
    return replay_loaded(
        log, cfg_override=cfg_override, tol=tol, out=out, allow_partial=allow_partial
    )
