"""Walk the records of an MCAP file that may be damaged, with mcap's own readers.

:func:`walk_records` reads with the sequential :class:`~mcap.stream_reader.StreamReader` (which
never needs the summary), so a file cut by a killed writer is read as far as it goes. When a
record in the middle cannot be read (a corrupt chunk) and the file still has its footer and
summary, the summary's chunk index says where the next chunk starts: the walk skips the damaged
chunk, records what it skipped, and goes on, so one bad chunk does not lose all later ones.
"""

from __future__ import annotations

import re
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from mcap.exceptions import EndOfFile, RecordLengthLimitExceeded
from mcap.reader import SeekingReader
from mcap.records import Channel, DataEnd, Footer, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.summary import Summary


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

    def skipped_note(self) -> str:
        """One phrase naming the damaged chunks that were skipped ("" if none)."""
        if not self.skipped:
            return ""
        where = ", ".join(f"{s.length} bytes at byte {s.offset}" for s in self.skipped[:4])
        more = f", ... ({len(self.skipped)} in all)" if len(self.skipped) > 4 else ""
        return (
            f"skipped {len(self.skipped)} damaged chunk(s) in the middle ({where}{more}; "
            f"{self.skipped[0].error}): the chunks after them were read from the chunk index"
        )


def _summary(fh: IO[bytes], size: int) -> Summary | None:
    """The file's summary section (chunk index, schemas, channels), None if it has none or it
    cannot be read (no footer)."""
    try:
        fh.seek(0)  # the seeking reader checks the magic where the file position is
        return SeekingReader(fh, record_size_limit=max(size, 1)).get_summary()
    except Exception:  # a cut or damaged tail: no usable index
        return None


def walk_records(fh: IO[bytes], state: Walk) -> Iterator[Any]:
    """Every record of ``fh`` in file order (chunks broken up, CRCs checked), stopping quietly
    at the first record that cannot be read unless the summary's chunk index lets the walk
    resume at the next chunk; ``state`` says where it stopped and what it skipped."""
    limit = max(state.size, 1)  # a garbage length never allocates more than the file
    reader = StreamReader(fh, validate_crcs=True, record_size_limit=limit)
    seen: set[tuple[type, int]] = set()
    summary: Summary | bool | None = False  # False: not looked up yet
    state.good_end = 0
    while True:
        try:
            for rec in reader.records:
                if isinstance(rec, Schema | Channel):
                    seen.add((type(rec), rec.id))
                elif isinstance(rec, Footer):
                    state.footer = True
                elif isinstance(rec, DataEnd):
                    state.data_end = True
                yield rec
                state.good_end = fh.tell()
            state.error = None
            return
        except Exception as exc:  # EndOfFile, CRC, zstd, garbage lengths
            state.error = exc
        if state.footer:
            return
        if summary is False:
            summary = _summary(fh, state.size)
            state.indexed = summary is not None
        if not state.indexed and (isinstance(state.error, EndOfFile) or state._cut_record()):
            return  # a cut file: nothing after the cut to resume at
        starts = sorted(
            c.chunk_start_offset
            for c in (summary.chunk_indexes if summary else [])
            if c.chunk_start_offset > state.good_end
        )
        if not starts:
            return
        failed = state.error
        state.skipped.append(
            Skip(state.good_end, starts[0] - state.good_end, f"{type(failed).__name__}: {failed}")
        )
        # the damaged chunk may have held schema or channel records the later messages need
        for rec in [*summary.schemas.values(), *summary.channels.values()]:
            if (type(rec), rec.id) not in seen:
                seen.add((type(rec), rec.id))
                yield rec
        fh.seek(starts[0])
        state.good_end = starts[0]
        reader = StreamReader(fh, skip_magic=True, validate_crcs=True, record_size_limit=limit)


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
