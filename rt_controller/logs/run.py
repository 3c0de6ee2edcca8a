"""A controller log as tables: :func:`load` and :class:`Run` (see :mod:`rt_controller.logs`).

Every table exists twice: as a dict of NumPy columns (:meth:`Run.arrays`, always available) and
as a pandas DataFrame built from those columns (``cycles``, ``diagnostics``, ``can_frames``,
``canopen_frames``, only with the ``analysis`` extra). Missing numbers are NaN; a field no
record had is no column. In ``can_frames`` an integer DBC signal is a pandas nullable integer
column instead (``Int64``, ``<NA>`` where a frame lacks it: :func:`integer_signals`), and so
is every whole-number field of a ``cia402`` log's CANopen frames (``can_frames`` and
``canopen_frames``: ``node``, ``statusword``, ``index``, ``sdo_value``, ...).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import re
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rt_controller import extras
from rt_controller.errors import LogError
from rt_controller.logtools.reader import LoadedLog, columns, read_hil_log

if TYPE_CHECKING:
    import pandas as pd

    from hal.config import RigConfig

TOPICS = ("cycle", "diagnostics", "can", "canopen")
"""The tables of a run, by the names ``hil export --topics`` takes."""

VECTOR_SUFFIXES: dict[str, tuple[str, ...]] = {"f": ("_x", "_y"), "f_pred": ("_x", "_y")}
"""Column suffixes of the image-plane vectors (``f`` -> ``f_x``, ``f_y``); every other vector
field is numbered from 1 like the joints (``q`` -> ``q1``, ``q2``; ``tau`` -> ``tau1``, ...)."""

_CAN_LEADING = ("t_ns", "time_s", "direction", "frame_id", "message", "dlc", "data", "is_fd")


def require(module: str, what: str) -> Any:
    """Import ``module`` of the ``analysis`` extra, or raise :class:`MissingExtraError` saying
    how to install it (``what`` is the job that needed it; the rule of
    :func:`rt_controller.extras.require`)."""
    return extras.require(module, what, "analysis")


def identifier(name: str) -> str:
    """``name`` as a column name: runs of characters other than letters, digits and ``_``
    become one ``_`` (``/controller/cycle`` -> ``controller_cycle``, ``events.enabled`` ->
    ``events_enabled``)."""
    return re.sub(r"[^0-9A-Za-z_]+", "_", str(name)).strip("_") or "value"


def load(path: str | Path, *, raw: bool = True) -> Run:
    """Read the controller log at ``path`` (``raw=False`` skips the CAN frames and vision
    messages: faster when only cycles and diagnostics are wanted).

    Raises :class:`~rt_controller.errors.LogError` (one line) for a missing file, a file that
    is not MCAP, and an MCAP file that hil did not write (``NotAHilLogError``, the rule of
    :func:`~rt_controller.logtools.reader.require_hil_log`). A log whose writer was killed loads
    as far as it goes, with ``truncated`` set and a note.
    """
    return Run(read_hil_log(path, raw=raw))


class Run:
    """One recorded run. Attributes are read from the log once; tables are built on first use.

    Args:
        log: what :func:`rt_controller.logtools.reader.read_log` read (``run.log``).
    """

    def __init__(self, log: LoadedLog) -> None:
        self.log = log
        self._arrays: dict[str, dict[str, np.ndarray]] = {}
        self._ints: dict[str, dict[str, list[Any]]] = {}
        """Per table, its integer columns as decoded (Python ints, None where absent: the DBC's
        integer signals of ``can``, a ``cia402`` log's whole-number CANopen fields): the
        DataFrame's nullable integer columns, exact."""
        self._int_dtypes: dict[str, dict[str, str]] = {}

    def __repr__(self) -> str:
        cut = ", truncated" if self.truncated else ""
        return f"<Run {self.path} {self.log.n_cycles} ticks{cut}>"

    # ------------------------------------------------------------------ what the log says

    @property
    def path(self) -> Path:
        return self.log.path

    @property
    def config(self) -> RigConfig | None:
        """The run's configuration as recorded (``hil.config`` metadata), None if absent."""
        return self.log.config

    @property
    def config_json(self) -> str | None:
        """The recorded configuration exactly as stored (JSON text)."""
        return self.log.config_json

    @property
    def config_dict(self) -> dict[str, Any] | None:
        """The recorded configuration as plain nested dicts."""
        return None if self.config_json is None else json.loads(self.config_json)

    @property
    def config_digest(self) -> str | None:
        """``sha256:`` and the hex SHA-256 of the recorded configuration's JSON text: two runs
        with the same digest ran the same configuration."""
        if self.config_json is None:
            return None
        return "sha256:" + hashlib.sha256(self.config_json.encode()).hexdigest()

    @property
    def info(self) -> dict[str, str]:
        """``hil.run`` metadata: law, rate_hz, clock, can, zenoh, recorder, start time, host..."""
        return self.log.run_info

    @property
    def recorder(self) -> dict[str, str]:
        """``hil.recorder`` metadata (written, dropped per topic); empty if not closed cleanly."""
        return self.log.recorder_info

    @property
    def truncated(self) -> bool:
        """The writer did not finish the file (killed, crashed, cut): read as far as it goes."""
        return self.log.truncated

    @property
    def notes(self) -> list[str]:
        return self.log.notes

    @property
    def topic_counts(self) -> dict[str, int]:
        """Messages per topic."""
        return self.log.topic_counts

    # -------------------------------------------------------------------- NumPy tables

    def arrays(self, topic: str = "cycle") -> dict[str, np.ndarray]:
        """The table ``topic`` (one of :data:`TOPICS`) as NumPy columns, keyed like the
        DataFrame's columns (``cycle`` also has ``tick``). Needs neither pandas nor the extra."""
        if topic not in TOPICS:
            raise LogError(f"unknown topic {topic!r}: choose from {', '.join(TOPICS)}")
        if topic not in self._arrays:
            build = {
                "cycle": self._cycle_arrays,
                "diagnostics": self._diag_arrays,
                "canopen": self._canopen_arrays,
            }
            self._arrays[topic] = build.get(topic, self._can_arrays)()
        return self._arrays[topic]

    def _t0_ns(self) -> int | None:
        t_ns = self.log.cycles.get("t_ns")
        if t_ns is not None and len(t_ns) and t_ns.dtype.kind in "iu":
            return int(t_ns[0])
        return None

    def _with_time(self, cols: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``time_s`` after ``t_ns``: seconds since the first tick's wake-up (the loop's
        monotonic clock), else since the table's first record."""
        t_ns = cols.get("t_ns")
        if t_ns is None or not len(t_ns) or t_ns.dtype.kind not in "iuf":
            return cols
        t0 = self._t0_ns()
        t0 = int(np.nanmin(t_ns)) if t0 is None else t0
        out: dict[str, np.ndarray] = {}
        for name, col in cols.items():
            out[name] = col
            if name == "t_ns":
                out["time_s"] = (t_ns - t0) / 1e9
        return out

    def _cycle_arrays(self) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {}
        for name, col in self.log.cycles.items():
            if col.ndim != 2:
                out[name] = col
                continue
            suffixes = VECTOR_SUFFIXES.get(name, ())
            if len(suffixes) != col.shape[1]:
                suffixes = tuple(str(j + 1) for j in range(col.shape[1]))
            for j, sfx in enumerate(suffixes):
                out[name + sfx] = np.ascontiguousarray(col[:, j])
        return out

    def _diag_arrays(self) -> dict[str, np.ndarray]:
        rows = []
        for rec in self.log.diagnostics:
            row = {k: rec.get(k) for k in ("t_ns", "tick", "final", "level")}
            for status in rec.get("status") or []:
                name = identifier(status.get("name", "status"))
                row[f"{name}_level"] = status.get("level")
                row[f"{name}_message"] = status.get("message")
                for key, value in (status.get("values") or {}).items():
                    row[f"{name}_{identifier(key)}"] = _scalar(value)
            rows.append(row)
        return self._with_time(columns(rows))

    def _can_arrays(self) -> dict[str, np.ndarray]:
        from hal.can_database import load_database

        frames = [("rx", f) for f in self.log.can_rx] + [("tx", f) for f in self.log.can_tx]
        frames.sort(key=lambda df: df[1].get("t_ns") or 0)  # stable: rx before tx on a tie
        cfg = self.log.config
        if cfg is not None and cfg.hardware.profile == "cia402":
            rows = [_canopen_decoded(direction, frame) for direction, frame in frames]
            return self._keep_ints("can", rows, self._with_time(columns(rows)))
        db = load_database().db
        rows = [_decoded(db, direction, frame) for direction, frame in frames]
        cols = self._with_time(columns(rows))
        dtypes = {k: v for k, v in integer_signals(db).items() if k in cols}
        self._int_dtypes["can"] = dtypes
        self._ints["can"] = {k: [row.get(k) for row in rows] for k in dtypes}
        order = [*_CAN_LEADING, "decode_error"]
        for msg in db.messages:
            for sig in msg.signals:
                order += [sig.name, f"{sig.name}_name"]
        rank = {name: i for i, name in enumerate(dict.fromkeys(order))}
        return {k: cols[k] for k in sorted(cols, key=lambda k: rank.get(k, len(rank)))}

    def _canopen_arrays(self) -> dict[str, np.ndarray]:
        rows = []
        for rec in self.log.canopen:
            row = {k: rec.get(k) for k in ("t_ns", "direction", "cob_id", "kind", "node", "data")}
            fields = rec.get("fields")
            row.update(fields if isinstance(fields, dict) else {})
            if "error" in rec:
                row["decode_error"] = rec["error"]
            rows.append(row)
        return self._keep_ints("canopen", rows, self._with_time(columns(rows)))

    def _keep_ints(
        self, topic: str, rows: list[dict[str, Any]], cols: dict[str, np.ndarray]
    ) -> dict[str, np.ndarray]:
        """Note the columns of ``cols`` that are float only because some rows lack them
        (every present value a Python int, not a bool): ``Int64`` in the DataFrame."""
        ints: dict[str, list[Any]] = {}
        for name, col in cols.items():
            if col.dtype.kind != "f":
                continue
            values = [row.get(name) for row in rows]
            present = [v for v in values if v is not None]
            if present and all(type(v) is int for v in present):
                ints[name] = values
        self._ints[topic] = ints
        self._int_dtypes[topic] = dict.fromkeys(ints, "Int64")
        return cols

    # --------------------------------------------------------------- pandas DataFrames

    def frame(self, topic: str) -> pd.DataFrame:
        """The table ``topic`` as a DataFrame (``cycle`` indexed by ``tick``)."""
        pd = require("pandas", "a DataFrame of the log")
        df = pd.DataFrame(self.arrays(topic))
        for name, dtype in self._int_dtypes.get(topic, {}).items():
            # from the decoded ints (a float column rounds beyond 2**53); a column of
            # other than whole numbers after all stays as it was
            with contextlib.suppress(TypeError, ValueError):
                df[name] = pd.array(self._ints[topic][name], dtype=dtype)
        if topic == "cycle" and "tick" in df.columns:
            df = df.set_index("tick")
        return df

    @cached_property
    def cycles(self) -> pd.DataFrame:
        """``/controller/cycle``: one row per tick (index ``tick``), every field of
        ``runtime/cycle_schema.json`` as columns, vectors split (``q1``, ``f_x``, ...)."""
        return self.frame("cycle")

    @cached_property
    def diagnostics(self) -> pd.DataFrame:
        """``/diagnostics``: ``t_ns``, ``time_s``, ``tick``, ``final``, ``level``, and per
        component (``can_rx``, ``features``, ``dsp``, ``controller``, ``recorder``) its
        ``NAME_level``, ``NAME_message`` and every counter as ``NAME_KEY``."""
        return self.frame("diagnostics")

    @cached_property
    def can_frames(self) -> pd.DataFrame:
        """Every raw CAN frame (``/hal/can/rx`` and ``/hal/can/tx``) in time order: ``t_ns``,
        ``time_s``, ``direction`` (rx/tx), ``frame_id``, ``message`` (DBC name, None for an
        unknown id), ``dlc``, ``data`` (hex), ``is_fd``, then one column per DBC signal
        (physical values): an integer signal (not float, scale 1, whole offset:
        :func:`integer_signals`) as a nullable ``Int64`` column (``UInt64`` for a 64-bit
        unsigned one), ``<NA>`` in the frames without it, every other signal float64 (NaN
        there). An enumerated signal (DBC ``VAL_``) is its raw value in such an integer column
        and its label in ``SIGNAL_name``, a string column (missing where absent), as before. A
        ``cia402`` log's CANopen frames are decoded by COB-ID instead: ``message`` is the
        kind (``nmt``, ``sync``, ``emcy``, ``tpdo1``, ``tpdo2``, ``rpdo1``, ``sdo_request``,
        ``sdo_response``, ``heartbeat``), ``node``, then ``statusword``, ``state``,
        ``position_actual``, ``velocity_actual``, ``torque_actual``, ``controlword``,
        ``target_torque`` (raw object values), EMCY ``code`` / ``register`` / ``text``,
        NMT ``command`` / ``target``, heartbeat ``nmt_state``, SDO ``sdo_service`` /
        ``index`` / ``subindex`` / ``sdo_value`` / ``abort_code`` (the spelling of the
        ``/hal/canopen`` topic: :func:`~rt_controller.runtime.record_encoding.canopen_dict`);
        each of these whole-number fields is an ``Int64`` column, ``<NA>`` where absent.

        ``time_s`` is ``t_ns`` in seconds since the first tick's wake-up (the loop's monotonic
        clock, negative before it): plant time only in a realtime run, not in lockstep. Align
        a frame with its tick by its ``Tick`` signal or by ``t_ns``."""
        return self.frame("can")

    @cached_property
    def canopen_frames(self) -> pd.DataFrame:
        """``/hal/canopen`` as recorded (a ``cia402`` log; empty for others and for logs
        recorded before the topic existed, whose ``can_frames`` decode the same way): one row
        per frame in the log's order, ``t_ns``, ``time_s``, ``direction``, ``cob_id``,
        ``kind``, ``node``, ``data``, then the decoded ``fields`` one column each (a
        whole-number field ``Int64``, ``<NA>`` where absent), and ``decode_error``."""
        return self.frame("canopen")


def integer_signals(db: Any) -> dict[str, str]:
    """The columns of ``can_frames`` that hold whole numbers, with their pandas dtype: the
    signal names of the cantools database ``db`` of which every signal (a name may be in
    several messages: ``Tick``, ``Counter``) is not a float (``is_float``), has ``scale`` 1
    and a whole ``offset``. ``UInt64`` for a 64-bit unsigned signal, else ``Int64``."""
    out: dict[str, str] = {}
    refused: set[str] = set()
    for msg in db.messages:
        for sig in msg.signals:
            whole = not sig.is_float and sig.scale == 1 and float(sig.offset).is_integer()
            if not whole:
                refused.add(sig.name)
            elif sig.length >= 64 and not sig.is_signed:
                out[sig.name] = "UInt64"
            else:
                out.setdefault(sig.name, "Int64")
    return {k: v for k, v in out.items() if k not in refused}


def _scalar(value: Any) -> Any:
    """A diagnostics value as one table cell: a list or dict (the cia402 profile's drives,
    fault events, deactivation steps) as its compact JSON text, so every column holds one
    type and the tables export (parquet refuses a column of lists)."""
    if isinstance(value, dict | list):
        return json.dumps(value, separators=(",", ":"), sort_keys=True)
    return value


def _canopen_decoded(direction: str, frame: dict[str, Any]) -> dict[str, Any]:
    """One CANopen frame record of a cia402 log as a table row: ``message`` is its kind
    (``sync``, ``tpdo1``, ``emcy``, ...), ``node``, then its decoded fields, as the log's
    ``/hal/canopen`` spells them (:func:`~rt_controller.runtime.record_encoding.canopen_dict`;
    ``decode_error`` for a payload that does not fit)."""
    from rt_controller.runtime.record_encoding import canopen_dict

    rec = canopen_dict(direction, frame)
    row: dict[str, Any] = {
        "t_ns": frame.get("t_ns"),
        "direction": direction,
        "frame_id": frame.get("arbitration_id"),
        "message": rec["kind"],
        "node": rec["node"],
        "dlc": frame.get("dlc"),
        "data": frame.get("data"),
        "is_fd": frame.get("is_fd"),
        **rec["fields"],
    }
    if "error" in rec:
        row["decode_error"] = rec["error"]
    return row


def _decoded(db: Any, direction: str, frame: dict[str, Any]) -> dict[str, Any]:
    """One CAN frame record as a table row, decoded with the DBC (cantools)."""
    fid = frame.get("arbitration_id")
    row: dict[str, Any] = {
        "t_ns": frame.get("t_ns"),
        "direction": direction,
        "frame_id": fid,
        "message": None,
        "dlc": frame.get("dlc"),
        "data": frame.get("data"),
        "is_fd": frame.get("is_fd"),
    }
    try:
        msg = db.get_message_by_frame_id(fid)
    except (KeyError, TypeError):
        return row
    row["message"] = msg.name
    try:
        signals = msg.decode(bytes.fromhex(frame.get("data") or ""), decode_choices=True)
    except Exception as exc:  # cantools raises several error types for a bad payload
        row["decode_error"] = f"{type(exc).__name__}: {exc}"
        return row
    for name, value in signals.items():
        if hasattr(value, "value") and hasattr(value, "name"):  # NamedSignalValue
            row[name], row[f"{name}_name"] = value.value, str(value.name)
        else:
            row[name] = value
    return row
