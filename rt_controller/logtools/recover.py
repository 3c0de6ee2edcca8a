"""A finished copy of a cut MCAP log (``hil recover``).

A recorder that was killed (SIGKILL, power loss) or a file cut in a copy leaves an MCAP file
without its summary section and footer, usually ending inside a chunk. ``hil`` reads such a
file as far as it goes, but mcap's own indexed reader and Foxglove do not
(``RecordLengthLimitExceeded``, no summary). :func:`recover` reads the records with mcap's
:class:`~mcap.stream_reader.StreamReader` up to the last complete one and writes them again
with mcap's :class:`~mcap.writer.Writer`: header, schemas, channels, messages, metadata and
attachments in their order, with chunk indexes, statistics, a summary section and the footer.
The input is never changed; the copy is written beside its final name and renamed into place.
"""

from __future__ import annotations

import stat
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from mcap.records import (
    Attachment,
    Channel,
    DataEnd,
    Footer,
    Header,
    Message,
    Metadata,
    Schema,
)
from mcap.writer import CompressionType, Writer

from hal.whole_file import written_whole
from rt_controller.errors import ControllerConfigError, LogError
from rt_controller.logtools.reader import (
    CYCLE_TOPIC,
    MAGIC,
    RECOVERED_METADATA,
    check_file,
    same_file,
)
from rt_controller.logtools.walk import Walk, walk_records

CHUNK_SIZE = 1024 * 1024
"""Chunk size of the copy (mcap's default; the recorder's small chunks only bound its loss)."""


@dataclass
class Recovery:
    """What :func:`recover` kept and lost (``hil recover --json`` prints :meth:`as_dict`)."""

    log: str
    out: str
    finished: bool = False
    """The input already had its footer (nothing was lost; the copy is a plain rewrite)."""
    input_bytes: int = 0
    kept_bytes: int = 0
    """Bytes of the input up to the end of its last complete record."""
    lost_bytes: int = 0
    """Bytes not kept: after the last complete record (a half-written chunk or record, never
    readable) and the damaged chunks skipped."""
    skipped: list[dict[str, Any]] = field(default_factory=list)
    """Damaged chunks in the middle stepped over with the chunk index: offset, length, error."""
    stopped: str = ""
    """Why the read ended (``footer``, ``end of file``, or the damage mcap reported)."""
    messages: int = 0
    cycles: int = 0
    """``/controller/cycle`` messages kept (the ticks of a controller log)."""
    schemas: int = 0
    channels: int = 0
    metadata: list[str] = field(default_factory=list)
    attachments: int = 0
    topics: dict[str, int] = field(default_factory=dict)
    orphans: int = 0
    """Messages whose channel record came nowhere before them (skipped; none in valid MCAP)."""

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    def line(self) -> str:
        """One line for people: what was kept and what was lost."""
        skipped = ""
        if self.skipped:
            where = ", ".join(f"{s['length']} B at byte {s['offset']}" for s in self.skipped[:4])
            skipped = f"; skipped {len(self.skipped)} damaged chunk(s) ({where})"
        if self.finished and not self.skipped:
            magic = "; its closing magic was missing" if self.stopped != "footer" else ""
            lost = f"nothing lost (the log was already finished{magic})"
        elif self.finished:
            lost = f"lost {self.lost_bytes} byte(s){skipped}"
        else:
            lost = f"lost the last {self.lost_bytes} byte(s) ({self.stopped}){skipped}"
        return (
            f"{self.out}: kept {self.messages} message(s) ({self.cycles} cycles) on "
            f"{self.channels} channel(s), {len(self.metadata)} metadata, {self.attachments} "
            f"attachment(s); {lost}"
        )


class NothingRecovered(LogError):
    """The input holds no message that could be read (cut or damaged inside its first chunk):
    no copy is written (``hil recover`` exits 1)."""


def default_out(log: Path) -> Path:
    """``LOG.recovered.mcap`` beside ``LOG``."""
    return log.with_name(f"{log.stem}.recovered{log.suffix or '.mcap'}")


def _check_paths(log: Path, out: Path) -> None:
    check_file(log)
    if same_file(out, log):
        raise ControllerConfigError(f"--out {out}: is the input log; recover never overwrites it")
    if out.exists() and not stat.S_ISREG(out.stat().st_mode):
        # the copy is renamed into place: that would replace a device node or FIFO
        raise ControllerConfigError(
            f"--out {out}: exists and is not a regular file (a device, FIFO or socket); "
            "recover writes only regular files"
        )


def recover(log: str | Path, out: str | Path | None = None) -> Recovery:
    """Write a finished copy of ``log`` to ``out`` (default :func:`default_out`).

    Raises :class:`LogError` for a missing or non-MCAP input or one cut before its header
    ended, :class:`NothingRecovered` (and writes nothing) when a cut or damaged input holds no
    message that could be read, :class:`ControllerConfigError` when ``out`` is the input
    itself.
    """
    log = Path(log)
    out = Path(out) if out is not None else default_out(log)
    _check_paths(log, out)
    result = Recovery(log=str(log), out=str(out), input_bytes=log.stat().st_size)
    with written_whole(out) as tmp, log.open("rb") as src, tmp.open("wb") as dst:
        _copy(src, dst, result)
    result.lost_bytes = result.input_bytes - result.kept_bytes
    return result


class _Rewriter:
    """The data records of the input, written again by ``writer`` under fresh ids."""

    def __init__(self, writer: Writer, result: Recovery) -> None:
        self.writer, self.result = writer, result
        self.schema_ids: dict[int, int] = {0: 0}  # 0: a channel without schema
        self.channel_ids: dict[int, int] = {}
        self.topics: dict[int, str] = {}
        self.counts: Counter[str] = Counter()

    def take(self, rec: Any) -> None:
        w, result = self.writer, self.result
        if isinstance(rec, Schema):
            self.schema_ids[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
        elif isinstance(rec, Channel):
            sid = self.schema_ids.get(rec.schema_id, 0)
            self.channel_ids[rec.id] = w.register_channel(
                rec.topic, rec.message_encoding, sid, dict(rec.metadata)
            )
            self.topics[rec.id] = rec.topic
        elif isinstance(rec, Message):
            if rec.channel_id not in self.channel_ids:
                result.orphans += 1  # no valid MCAP has a message before its channel
                return
            cid = self.channel_ids[rec.channel_id]
            w.add_message(cid, rec.log_time, rec.data, rec.publish_time, rec.sequence)
            self.counts[self.topics[rec.channel_id]] += 1
        elif isinstance(rec, Metadata):
            w.add_metadata(rec.name, dict(rec.metadata))
            result.metadata.append(rec.name)
        elif isinstance(rec, Attachment):
            w.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
            result.attachments += 1

    def finish(self) -> None:
        """Add the :data:`RECOVERED_METADATA` record (where the copy came from, what it lost)
        and finish the file."""
        result = self.result
        self.writer.add_metadata(
            RECOVERED_METADATA,
            {
                "from": result.log,
                "input_bytes": str(result.input_bytes),
                "kept_bytes": str(result.kept_bytes),
                "stopped": result.stopped,
                "skipped_bytes": str(sum(s["length"] for s in result.skipped)),
            },
        )
        self.writer.finish()
        result.topics = dict(self.counts)
        result.messages = sum(self.counts.values())
        result.cycles = self.counts[CYCLE_TOPIC]
        result.schemas = len(self.schema_ids) - 1
        result.channels = len(self.channel_ids)


def _copy(src: Any, dst: Any, result: Recovery) -> None:
    """Walk ``src`` (:func:`walk_records`: damaged chunks in the middle of a file with a chunk
    index are skipped) into a :class:`_Rewriter` on ``dst`` until the footer or the first
    record that cannot be read; ``result`` says where and why it stopped."""
    state = Walk(size=result.input_bytes)
    rewriter: _Rewriter | None = None
    data_end = False
    result.kept_bytes = len(MAGIC)
    for rec in walk_records(src, state):
        if isinstance(rec, Header):
            writer = Writer(dst, chunk_size=CHUNK_SIZE, compression=CompressionType.ZSTD)
            writer.start(profile=rec.profile, library=rec.library)
            rewriter = _Rewriter(writer, result)
        elif rewriter is None:
            raise LogError(f"{result.log}: the first record is not the MCAP header")
        elif isinstance(rec, Footer):
            result.finished, result.stopped = True, "footer"
            continue  # the walk goes on to check the closing magic
        elif data_end:
            continue  # the summary section repeats what was read; the writer makes its own
        elif isinstance(rec, DataEnd):
            data_end, result.stopped = True, "cut in the summary section (all data kept)"
        else:
            rewriter.take(rec)
        if not data_end or isinstance(rec, DataEnd):
            result.kept_bytes = src.tell()
    if state.footer and state.error is not None:  # the footer read, then the closing magic not
        result.finished, result.stopped = True, "footer; the closing magic was missing"
    elif state.error is not None:
        at_boundary = state.good_end >= result.input_bytes
        damage = state.damage()
        if damage.startswith("ends"):
            damage = "end of file" if at_boundary else "cut inside a record"
        result.stopped = result.stopped or damage
    elif not result.finished:
        result.stopped = result.stopped or "end of file"
    result.skipped = [asdict(s) for s in state.skipped]
    if rewriter is None:
        raise LogError(f"{result.log}: cut before the end of its MCAP header: nothing to recover")
    if result.finished:
        result.kept_bytes = result.input_bytes
    result.kept_bytes -= sum(s.length for s in state.skipped)
    if not rewriter.counts and (not result.finished or state.skipped):
        raise NothingRecovered(f"{result.log}: nothing to recover: {_nothing_read(state, result)}")
    rewriter.finish()


def _nothing_read(state: Walk, result: Recovery) -> str:
    """Why a cut or damaged input gave no message: its damaged chunks, where the read stopped."""
    parts = []
    if state.skipped:
        where = ", ".join(f"{s.length} bytes at byte {s.offset}" for s in state.skipped[:4])
        parts.append(f"its damaged chunk(s) were skipped ({where}; {state.skipped[0].error})")
    if not result.finished and state.error is not None:
        parts.append(
            f"the record from byte {state.good_end} on cannot be read ({result.stopped}; the "
            f"file has {state.size} bytes)"
        )
    elif not result.finished:
        parts.append(f"the file ends at byte {state.size}, before any message")
    return f"no message could be read: {'; '.join(parts)}; no copy written"
