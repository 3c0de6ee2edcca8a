"""Damaged copies of MCAP logs for the log tools' tests: where the chunks and their message
indexes are (from mcap's own reader), and a copy with chosen bytes flipped."""

from __future__ import annotations

from pathlib import Path

from mcap.reader import make_reader
from mcap.records import ChunkIndex


def chunk_indexes(path: Path) -> list[ChunkIndex]:
    """The chunk index entries of a finished log, in file order."""
    with path.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    return sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)


def chunk_starts(path: Path) -> list[int]:
    """Where each chunk of a finished log starts, in file order."""
    return [c.chunk_start_offset for c in chunk_indexes(path)]


def message_index_starts(path: Path) -> list[int]:
    """Where each message index record of a finished log starts, in file order."""
    return sorted(o for c in chunk_indexes(path) for o in c.message_index_offsets.values())


def damaged_copy(log: Path, tmp_path: Path, at: int, n: int, name: str = "flip.mcap") -> Path:
    """``log`` with ``n`` bytes flipped from byte ``at``, as ``tmp_path / name``."""
    data = bytearray(log.read_bytes())
    for i in range(at, at + n):
        data[i] ^= 0xFF
    bad = tmp_path / name
    bad.write_bytes(bytes(data))
    return bad
