"""Walk the records of an MCAP file that may be damaged, with mcap's own readers.

:func:`walk_records` reads with the sequential :class:`~mcap.stream_reader.StreamReader` (which
never needs the summary), so a file cut by a killed writer is read as far as it goes. When a
record in the middle cannot be read (a corrupt chunk) and the file still has its footer and
summary, the summary says where the next record it indexes starts (a chunk, a metadata record,
the data end): the walk skips the damaged chunk, records what it skipped, and goes on, so one
bad chunk (the last one too) does not lose all later records nor the footer. Damage confined to
the message indexes after a chunk read whole loses no record: it is noted apart
(``Walk.index_damage``), not as a skipped chunk.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from mcap.exceptions import EndOfFile, RecordLengthLimitExceeded
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, DataEnd, Footer, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.summary import Summary

_FOOTER_AND_MAGIC = 1 + 8 + 8 + 8 + 4 + 8
"""Bytes of the footer record (opcode, length, summary start, summary offset start, CRC) and
the closing magic."""
_DATA_END_SIZE = 1 + 8 + 4
"""Bytes of the data end record (opcode, length, data section CRC)."""
_SINCE_KEPT = 4096
"""Record starts after the last chunk the walk keeps (to find where to resume)."""


@dataclass
class Skip:
    """A damaged stretch the walk stepped over: ``length`` bytes from ``offset``."""

    offset: int
    length: int
    error: str


@dataclass
class Walk:
    """How a :func:`walk_records` went: filled in while it runs."""

    size: int
    footer: bool = False
    """The footer record was read (the writer finished the file)."""
    error: BaseException | None = None
    """What ended the read before the footer (None: footer, or nothing after the header)."""
    good_end: int = 0
    """Offset just after the last record read whole (where the failed record starts)."""
    skipped: list[Skip] = field(default_factory=list)
    data_end: bool = False
    """The data end record was read: every data record of the file was (a cut after it is in
    the summary section, which only repeats what was read)."""
    index_damage: list[Skip] = field(default_factory=list)
    """Damaged message indexes after chunks that were read whole: stepped over, no record lost
    (a chunk's message indexes only repeat where its messages are)."""
    indexed: bool = False
    """The file has a readable footer and summary: a record running past its end is damage
    in the middle (a garbage length), not a cut."""

    @property
    def skipped_bytes(self) -> int:
        return sum(s.length for s in self.skipped)

    def where(self) -> str:
        """Where the read stopped, for people: ``at byte N of M``."""
        return f"at byte {self.good_end} of {self.size}"

    def damage(self) -> str:
        """One phrase for why the read stopped early ("" after the footer)."""
        if self.error is None:
            return ""
        if self.footer:
            return "the closing magic after the footer is missing or damaged"
        if not self.indexed and (isinstance(self.error, EndOfFile) or self._cut_record()):
            at_boundary = self.good_end >= self.size
            return "ends without a footer" + ("" if at_boundary else f", cut {self.where()}")
        return f"damaged {self.where()} ({type(self.error).__name__}: {self.error})"

    def _cut_record(self) -> bool:
        """The failed record's length runs past the end of the file: a cut, not damage (the
        length of a record cut inside its header is garbage, and is not judged)."""
        if not isinstance(self.error, RecordLengthLimitExceeded):
            return False
        m = re.match(r"(\w+) record has length (\d+)", str(self.error))
        if m is None or m.group(1) == "unknown":
            return False
        return self.good_end + 9 + int(m.group(2)) > self.size

    def index_note(self) -> str:
        """One phrase naming the damaged message indexes stepped over ("" if none)."""
        return _listed(
            self.index_damage,
            "stepped over damaged message index(es) after {n} chunk(s) (at {where}; {error}): "
            "the chunks were read whole, no record lost",
            lambda s: f"byte {s.offset}",
        )

    def skipped_note(self) -> str:
        """One phrase naming the damaged chunks that were skipped ("" if none)."""
        return _listed(
            self.skipped,
            "skipped {n} damaged chunk(s) ({where}; {error}): the records after them were "
            "read from the summary's index",
            lambda s: f"{s.length} bytes at byte {s.offset}",
        )


def _listed(skips: list[Skip], line: str, place: Callable[[Skip], str]) -> str:
    """``line`` filled in for ``skips`` (the first four placed, the first's error), or ""."""
    if not skips:
        return ""
    where = ", ".join(place(s) for s in skips[:4])
    where += f", ... ({len(skips)} in all)" if len(skips) > 4 else ""
    return line.format(n=len(skips), where=where, error=skips[0].error)


def _summary(fh: IO[bytes], size: int) -> Summary | None:
    """The file's summary section (chunk index, schemas, channels), None if it has none or it
    cannot be read (no footer)."""
    try:
        fh.seek(0)  # the seeking reader checks the magic where the file position is
        return SeekingReader(fh, record_size_limit=max(size, 1)).get_summary()
    except Exception:  # a cut or damaged tail: no usable index
        return None


def _data_end_offset(fh: IO[bytes], size: int) -> int | None:
    """Where the data end record starts (just before the summary section the footer points
    at), None if the footer cannot be read or no data end record is there."""
    try:
        fh.seek(size - _FOOTER_AND_MAGIC)
        footer = next(StreamReader(fh, skip_magic=True, record_size_limit=size).records)
        at = footer.summary_start - _DATA_END_SIZE
        fh.seek(at)
        ok = isinstance(footer, Footer) and at > 0 and fh.read(1) == bytes([Opcode.DATA_END])
    except Exception:
        return None
    return at if ok else None


def _layout(
    fh: IO[bytes], summary: Summary, size: int
) -> tuple[list[int], dict[int, tuple[int, int]]]:
    """Where the records the summary indexes start (chunks, metadata, attachments, the data
    end), in file order; and where each chunk's message indexes start and end, by chunk
    start."""
    starts = {c.chunk_start_offset for c in summary.chunk_indexes}
    starts |= {m.offset for m in summary.metadata_indexes}
    starts |= {a.offset for a in summary.attachment_indexes}
    data_end = _data_end_offset(fh, size)
    if data_end is not None:
        starts.add(data_end)
    indexes = {}
    for c in summary.chunk_indexes:
        after = c.chunk_start_offset + c.chunk_length
        indexes[c.chunk_start_offset] = (after, after + c.message_index_length)
    return sorted(starts), indexes


def _records(reader: StreamReader, fh: IO[bytes], state: Walk) -> Iterator[tuple[int, Any]]:
    """``(where the record starts, record)`` for each record; a chunk comes whole (its CRC
    checked) and is then followed by its records; ``state.good_end`` is kept up to date."""
    for rec in reader.records:
        at = state.good_end
        if isinstance(rec, Chunk):
            inner = breakup_chunk(rec, validate_crc=True)
            state.good_end = fh.tell()
            yield at, rec
            for r in inner:
                yield at, r
        else:
            state.good_end = fh.tell()
            yield at, rec


def walk_records(fh: IO[bytes], state: Walk) -> Iterator[Any]:
    """Every record of ``fh`` in file order (chunks broken up, CRCs checked), stopping quietly
    at the first record that cannot be read unless the summary lets the walk resume at the
    next record it indexes (a chunk, a metadata or attachment record, the data end); ``state``
    says where it stopped, the damaged chunks it skipped and the damaged message indexes."""
    limit = max(state.size, 1)  # a garbage length never allocates more than the file
    reader = StreamReader(fh, validate_crcs=True, record_size_limit=limit, emit_chunks=True)
    seen: set[tuple[type, int]] = set()
    summary: Summary | bool | None = False  # False: not looked up yet
    known: list[int] = []
    indexes: dict[int, tuple[int, int]] = {}
    chunk_at = -1  # where the last chunk read whole starts
    since: list[int] = []  # where the records read after it start (the first: where resumed)
    state.good_end = 0
    while True:
        try:
            for at, rec in _records(reader, fh, state):
                if isinstance(rec, Chunk):
                    chunk_at, since = at, []
                    continue
                if at != chunk_at and (not since or since[-1] != at):
                    since.append(at)
                    if len(since) > _SINCE_KEPT:  # a file without chunks: keep the last ones
                        del since[: _SINCE_KEPT // 2]
                if isinstance(rec, Schema | Channel):
                    seen.add((type(rec), rec.id))
                elif isinstance(rec, Footer):
                    state.footer = True
                elif isinstance(rec, DataEnd):
                    state.data_end = True
                yield rec
            state.error = None
            return
        except Exception as exc:  # EndOfFile, CRC, zstd, garbage lengths
            state.error = exc
        if state.footer:
            return
        if summary is False:
            summary = _summary(fh, state.size)
            state.indexed = summary is not None
            if summary is not None:
                known, indexes = _layout(fh, summary, state.size)
        if not state.indexed and (isinstance(state.error, EndOfFile) or state._cut_record()):
            return  # a cut file: nothing after the cut to resume at
        if state.data_end:
            return  # the damage is in the summary section: every data record was read
        # the failed record itself, if the summary says one starts there, else the last one
        # read that does (a garbage length in a message index may have read on past the next)
        last_known = max([chunk_at, *(a for a in since if a in known)])
        floor = state.good_end if state.good_end in known else last_known
        after = [k for k in known if k > floor]
        if not after:
            return
        resume, failed = after[0], state.error
        what = f"{type(failed).__name__}: {failed}"
        at, end = indexes.get(chunk_at, (-1, -1))
        if floor == chunk_at >= 0 and resume <= end:  # only the chunk's message indexes
            state.index_damage.append(Skip(at, resume - at, what))
        else:
            state.skipped.append(Skip(floor, resume - floor, what))
        # the damaged chunk may have held schema or channel records the later messages need
        for rec in [*summary.schemas.values(), *summary.channels.values()]:
            if (type(rec), rec.id) not in seen:
                seen.add((type(rec), rec.id))
                yield rec
        fh.seek(resume)
        state.good_end, chunk_at, since = resume, -1, []
        reader = StreamReader(
            fh, skip_magic=True, validate_crcs=True, record_size_limit=limit, emit_chunks=True
        )


def topic_messages(path: Path, topics: Collection[str]) -> Iterator[tuple[str, Message]]:
    """``(topic, message)`` for the messages of ``path`` on ``topics``, in file order, read as
    far as the file goes (:func:`walk_records`: a cut or damaged file never raises here)."""
    names: dict[int, str] = {}
    with path.open("rb") as fh:
        for rec in walk_records(fh, Walk(size=path.stat().st_size)):
            if isinstance(rec, Channel):
                names[rec.id] = rec.topic
            elif isinstance(rec, Message) and names.get(rec.channel_id) in topics:
                yield names[rec.channel_id], rec
