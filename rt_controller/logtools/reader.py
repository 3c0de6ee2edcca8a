"""Read a controller MCAP log robustly, including one whose writer was killed.

:func:`read_log` walks the file with mcap's sequential :class:`~mcap.stream_reader.StreamReader`
(it never needs the summary section), keeps every record of every complete chunk, and stops
quietly at the first record it cannot read: a file without footer is reported as ``truncated``
with a note, never as a crash. Cycle records come back as numpy columns.
"""

from __future__ import annotations

import json
import os
import stat
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.records import Channel, Header, Message, Metadata, Schema

from hal.config import RigConfig, config_from_json
from hal.errors import HalConfigError
from rt_controller.errors import LogError, NotAHilLogError
from rt_controller.logtools.walk import Walk, walk_records
from rt_controller.runtime.recorder import (
    CAN_RX_TOPIC,
    CAN_TX_TOPIC,
    CANOPEN_TOPIC,
    CHUNK_SIZE,
    CONFIG_METADATA,
    CYCLE_TOPIC,
    DIAGNOSTICS_TOPIC,
    EVENTS_TOPIC,
    PARAMETERS_TOPIC,
    RECORDER_METADATA,
    RUN_METADATA,
    VISION_TOPIC,
)

MAGIC = b"\x89MCAP0\r\n"
RECOVERED_METADATA = "hil.recovered"
"""The metadata record ``hil recover`` adds to its copy: ``from`` (the input's path),
``input_bytes``, ``kept_bytes``, ``stopped`` (why the read ended), ``skipped_bytes``."""
MAX_CHANNELS_NAMED = 8
"""How many channels a "not a hil log" message names."""


@dataclass
class LoadedLog:
    """Everything :func:`read_log` found in one MCAP file."""

    path: Path
    config: RigConfig | None = None
    """The run's configuration (``hil.config`` metadata), None if absent or invalid."""
    config_json: str | None = None
    run_info: dict[str, str] = field(default_factory=dict)
    """``hil.run`` metadata: law, rate_hz, clock, start time, host, versions, ..."""
    recorder_info: dict[str, str] = field(default_factory=dict)
    """``hil.recorder`` metadata written at a clean close (written/dropped counters)."""
    recovered_info: dict[str, str] | None = None
    """``hil.recovered`` metadata: the log is a copy ``hil recover`` made of a cut one."""
    cycles: dict[str, np.ndarray] = field(default_factory=dict)
    """One column per cycle field: bools, int64, float64 (null -> NaN), (n, k) for vectors."""
    can_rx: list[dict[str, Any]] = field(default_factory=list)
    can_tx: list[dict[str, Any]] = field(default_factory=list)
    canopen: list[dict[str, Any]] = field(default_factory=list)
    """``/hal/canopen`` records (a ``cia402`` run's CAN frames decoded by the recorder)."""
    vision: list[dict[str, Any]] = field(default_factory=list)
    diagnostics: list[dict[str, Any]] = field(default_factory=list)
    """``/diagnostics`` records (always kept: about one a second)."""
    parameters: list[dict[str, Any]] = field(default_factory=list)
    """``/controller/parameters`` records: online changes, accepted or refused (always kept)."""
    events: list[dict[str, Any]] = field(default_factory=list)
    """``/controller/events`` records: operator actions (marks, arm, disarm), done or refused."""
    topic_counts: dict[str, int] = field(default_factory=dict)
    """Messages read per topic (also for raw topics that were not kept)."""
    rejected: dict[str, int] = field(default_factory=dict)
    """Messages per topic that were read but skipped, their payload not a record of the topic
    (not a JSON object; on ``/controller/cycle``, also one without an integer ``tick``): the
    log is damaged there. Counted only for the topics read (:func:`read_log`'s ``raw``)."""
    schemas: dict[str, str] = field(default_factory=dict)
    """Schema name per topic."""
    channels: list[str] = field(default_factory=list)
    """The topic of every channel found, in file order (with or without messages)."""
    library: str | None = None
    """The MCAP header's ``library`` (the writer's name, ``hil-rt_controller/VERSION`` for the
    controller's logs); None if the header could not be read."""
    truncated: bool = False
    """Not all of the log was read: no footer (the writer did not finish it: killed, crashed,
    cut), or damaged chunks in the middle were skipped (``walk.skipped``)."""
    walk: Walk | None = None
    """How the read went: where it stopped, the damaged chunks it skipped."""
    notes: list[str] = field(default_factory=list)

    @property
    def n_cycles(self) -> int:
        col = self.cycles.get("tick")
        return 0 if col is None else len(col)

    def column(self, name: str) -> np.ndarray | None:
        """A cycle field as an array, or None if no record had it."""
        return self.cycles.get(name)

    @property
    def rate_hz(self) -> float | None:
        """Control rate: from the config, else from ``hil.run``, else None."""
        if self.config is not None:
            return self.config.rates.control_hz
        try:
            return float(self.run_info["rate_hz"])
        except (KeyError, ValueError):
            return None


def _is_vector(v: Any) -> bool:
    return isinstance(v, list)


def _column(values: list[Any]) -> np.ndarray:
    """Best numpy representation of one field over all records (None = missing)."""
    present = [v for v in values if v is not None]
    if not present:
        return np.full(len(values), np.nan)
    if all(isinstance(v, bool) for v in present):
        if len(present) == len(values):
            return np.array(values, dtype=bool)
        return np.array([np.nan if v is None else float(v) for v in values])
    if all(isinstance(v, int) and not isinstance(v, bool) for v in present):
        if len(present) == len(values):
            return np.array(values, dtype=np.int64)
        return np.array([np.nan if v is None else v for v in values], dtype=float)
    if all(isinstance(v, int | float) and not isinstance(v, bool) for v in present):
        return np.array([np.nan if v is None else v for v in values], dtype=float)
    if all(_is_vector(v) for v in present):
        width = max(len(v) for v in present)
        out = np.full((len(values), width), np.nan)
        for i, v in enumerate(values):
            if v is not None:
                out[i, : len(v)] = [np.nan if x is None else x for x in v]
        return out
    return np.array(values, dtype=object)


def columns(records: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    """Turn a list of cycle dicts into numpy columns (keys in first-seen order)."""
    keys: dict[str, None] = {}
    for r in records:
        keys.update(dict.fromkeys(r))
    out = {}
    for k in keys:
        try:
            out[k] = _column([r.get(k) for r in records])
        except (TypeError, ValueError):
            out[k] = np.array([r.get(k) for r in records], dtype=object)
    return out


def check_file(path: Path) -> None:
    """Raise :class:`LogError` (one line) unless ``path`` is a readable file that starts with
    the MCAP magic."""
    try:
        mode = path.stat().st_mode
    except OSError:
        mode = None  # open() below names what is wrong
    if mode is not None and not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):  # FIFO: blocks
        raise LogError(f"{path}: not a regular file (a pipe or a device), not an MCAP file")
    try:
        with path.open("rb") as fh:
            head = fh.read(len(MAGIC))
    except FileNotFoundError:
        raise LogError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise LogError(f"{path}: is a directory, not an MCAP file") from None
    except OSError as exc:
        raise LogError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    if not head:  # a recorder that died before its first byte, a file made by hand
        raise LogError(f"{path}: empty file (0 bytes): nothing was recorded, not an MCAP file")
    if head != MAGIC:
        raise LogError(f"{path}: not an MCAP file (bad magic)")


def same_file(a: str | Path, b: str | Path) -> bool:
    """Whether ``a`` and ``b`` name one file: one existing file through a link or another
    spelling, or one path spelt twice (``./x`` and ``x``) though it does not exist yet."""
    if Path(a).resolve() == Path(b).resolve():
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:  # either is missing
        return False


def read_log(path: str | Path, *, raw: bool = True) -> LoadedLog:
    """Read ``path``; ``raw=False`` counts the CAN (raw and decoded) and vision messages
    without keeping them.

    Raises :class:`LogError` (one clear line) for a missing file or a non-MCAP file; any damage
    after the magic (truncation, a half-written chunk) ends the read with ``truncated`` set.
    """
    path = Path(path)
    check_file(path)
    out = LoadedLog(path=path)
    channels: dict[int, str] = {}
    schema_names: dict[int, str] = {}
    cycle_records: list[dict[str, Any]] = []
    raw_lists = {
        CAN_RX_TOPIC: out.can_rx,
        CAN_TX_TOPIC: out.can_tx,
        CANOPEN_TOPIC: out.canopen,
        VISION_TOPIC: out.vision,
    }
    counts: Counter[str] = Counter()
    bad: Counter[tuple[str, str]] = Counter()
    state = Walk(size=path.stat().st_size)
    with path.open("rb") as fh:
        # the walk stops quietly at damage it cannot step over (state says where)
        for rec in walk_records(fh, state):
            if isinstance(rec, Message):
                topic = channels.get(rec.channel_id, f"#{rec.channel_id}")
                counts[topic] += 1
                keep = topic in (CYCLE_TOPIC, DIAGNOSTICS_TOPIC, PARAMETERS_TOPIC, EVENTS_TOPIC)
                if not keep and not (raw and topic in raw_lists):
                    continue
                obj, why = _payload(topic, rec.data)
                if obj is None:
                    bad[(topic, why)] += 1
                elif topic == CYCLE_TOPIC:
                    cycle_records.append(obj)
                elif topic == DIAGNOSTICS_TOPIC:
                    out.diagnostics.append(obj)
                elif topic == PARAMETERS_TOPIC:
                    out.parameters.append(obj)
                elif topic == EVENTS_TOPIC:
                    out.events.append(obj)
                else:
                    raw_lists[topic].append(obj)
            elif isinstance(rec, Channel):
                channels[rec.id] = rec.topic
                if rec.schema_id in schema_names:
                    out.schemas[rec.topic] = schema_names[rec.schema_id]
            elif isinstance(rec, Schema):
                schema_names[rec.id] = rec.name
            elif isinstance(rec, Metadata):
                _take_metadata(out, rec)
            elif isinstance(rec, Header):
                out.library = rec.library
    out.walk = state
    if state.skipped:
        out.truncated = True
        out.notes.append(f"log {state.skipped_note()}")
    if state.index_damage:  # redundant with the chunks, which were read whole: nothing lost
        out.notes.append(f"log: {state.index_note()}")
    if not state.footer:
        out.truncated = True
        out.notes.append(_damage_note(state, counts[CYCLE_TOPIC]))
    elif state.error is not None:
        out.notes.append(f"log: {state.damage()}: every record was read")
    for (topic, why), n in bad.items():
        out.rejected[topic] = out.rejected.get(topic, 0) + n
        out.notes.append(f"{n} {topic} message(s) were {why} and were skipped")
    if not state.footer and not out.recorder_info:
        out.notes.append(f"the recorder did not close the file ({_unclosed_cause(path)})")
    out.cycles = columns(cycle_records)
    out.topic_counts = dict(counts)
    out.channels = list(dict.fromkeys(channels.values()))
    if out.config is None and out.config_json is None:
        out.notes.append("no hil.config metadata: the run configuration is unknown")
    return out


def _unclosed_cause(path: Path) -> str:
    """Why a log may have no footer: its filesystem is (nearly) full, or the recorder died."""
    try:
        st = os.statvfs(path)
    except OSError:
        return "process killed or crashed?"
    free = st.f_bavail * st.f_frsize
    if free < CHUNK_SIZE:  # less than the recorder's next chunk
        return f"{free} bytes left on its filesystem: the disk probably filled up while recording"
    return "process killed or crashed?"


def _payload(topic: str, data: bytes) -> tuple[dict[str, Any] | None, str]:
    """The record a message holds, or None and why it is none: its payload is not a JSON
    object, or (a cycle) has no integer ``tick``, the field every tool indexes ticks by."""
    try:
        obj = json.loads(data)
    except (ValueError, UnicodeDecodeError):
        obj = None
    if not isinstance(obj, dict):
        return None, "not valid JSON objects"
    tick = obj.get("tick")
    if topic == CYCLE_TOPIC and (not isinstance(tick, int) or isinstance(tick, bool)):
        return None, "JSON objects without an integer tick (not cycle records)"
    return obj, ""


def read_hil_log(path: str | Path, *, raw: bool = True) -> LoadedLog:
    """:func:`read_log`, refusing a file that holds no controller run (:func:`require_hil_log`)."""
    return require_hil_log(read_log(path, raw=raw))


def require_hil_log(log: LoadedLog) -> LoadedLog:
    """``log`` if it is a controller log: it has the run's ``hil.config``/``hil.run`` metadata
    (a run stopped before its first tick, or killed before its first chunk was written, still
    has them; damaged records are then its notes and problems) or a ``/controller/cycle``
    channel of which no message is unreadable or at least one is readable (a channel name
    alone does not make a hil log). Else :class:`NotAHilLogError`, one line naming the count
    of unreadable cycle records, or the channels the file has: an MCAP written by another
    tool, or a hil log cut before any of its records."""
    if log.config_json is not None or log.run_info:
        return log
    unreadable = log.rejected.get(CYCLE_TOPIC, 0)
    if unreadable and not log.n_cycles:
        raise NotAHilLogError(
            f"{log.path}: not a hil log: none of its {unreadable} {CYCLE_TOPIC} record(s) is "
            "readable and it has no hil.config or hil.run metadata"
        )
    if CYCLE_TOPIC in log.channels:
        return log
    shown = ", ".join(log.channels[:MAX_CHANNELS_NAMED]) or "none"
    if len(log.channels) > MAX_CHANNELS_NAMED:
        shown += f", ... ({len(log.channels)} in all)"
    cut = ""
    if log.truncated:
        cut = f"; the file is cut short after {log.path.stat().st_size} bytes"
    raise NotAHilLogError(
        f"{log.path}: not a hil log: no {CYCLE_TOPIC} records (channels: {shown}{cut})"
    )


def _damage_note(state: Walk, n_cycles: int) -> str:
    if state.error is None or state.damage().startswith("ends"):
        what = f"{state.damage() or 'ends without a footer'} (the writer did not finish it)"
    else:
        what = f"is {state.damage()}"
    return f"log {what}: read as far as it goes, {n_cycles} cycle messages in complete chunks"


def _take_metadata(out: LoadedLog, rec: Metadata) -> None:
    if rec.name == CONFIG_METADATA:
        out.config_json = rec.metadata.get("json")
        if out.config_json is None:
            out.notes.append("hil.config metadata has no 'json' key")
            return
        try:
            out.config = config_from_json(out.config_json)
        except HalConfigError as exc:
            out.notes.append(f"hil.config metadata is not a valid configuration: {exc}")
    elif rec.name == RUN_METADATA:
        out.run_info = dict(rec.metadata)
    elif rec.name == RECORDER_METADATA:
        out.recorder_info = dict(rec.metadata)
    elif rec.name == RECOVERED_METADATA:
        out.recovered_info = dict(rec.metadata)
