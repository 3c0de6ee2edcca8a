"""Damaged logs and unsafe output paths across the log tools: one corrupt chunk in the middle
of a finished log is skipped with the chunk index (not everything after it lost), a log missing
only its closing magic is complete for every tool, `recover --out` refuses device nodes and
FIFOs, `replay --out` refuses a hard link to its input, `export` refuses a log without readable
cycles, and one unreadable log among several does not stop `hil report` from reporting the rest."""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import pytest
from mcap.reader import make_reader

from hal.config import RigConfig
from rt_controller.cli import main
from rt_controller.logtools.reader import read_log
from rt_controller.logtools.recover import recover
from tests.controller.test_logs import record
from tests.controller.test_replay import record_run

TICKS = 400


@pytest.fixture(scope="module")
def whole(tmp_path_factory) -> Path:
    """A finished log of many small chunks."""
    return record(tmp_path_factory.mktemp("damage") / "whole.mcap", TICKS, chunk=2048)


def _corrupt_middle_chunk(src: Path, dst: Path) -> tuple[int, int]:
    """``src`` with 64 bytes of its middle chunk overwritten, as ``dst``: (offset, length)."""
    with src.open("rb") as fh:
        chunks = sorted(
            make_reader(fh).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset
        )
    mid = chunks[len(chunks) // 2]
    data = bytearray(src.read_bytes())
    at = mid.chunk_start_offset + mid.chunk_length // 2
    data[at : at + 64] = b"\xa5" * 64
    dst.write_bytes(bytes(data))
    return mid.chunk_start_offset, mid.chunk_length


def test_one_corrupt_chunk_in_the_middle_is_skipped(whole, tmp_path, capsys):
    bad = tmp_path / "mid.mcap"
    offset, length = _corrupt_middle_chunk(whole, bad)
    log = read_log(bad)
    assert log.truncated and log.walk.footer and TICKS // 2 < log.n_cycles < TICKS
    assert log.column("tick")[-1] == TICKS - 1  # the chunks after the damage were read
    note = " ".join(log.notes)
    assert f"at byte {offset}" in note and "near its end" not in note
    assert "did not close" not in note
    result = recover(bad, tmp_path / "rec.mcap")
    assert result.finished and [s["offset"] for s in result.skipped] == [offset]
    # the chunk and its message indexes, up to the next chunk
    assert result.lost_bytes == result.skipped[0]["length"] >= length
    assert result.cycles == log.n_cycles
    assert main(["info", str(bad), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["damaged"] and "damaged chunk(s)" in " ".join(info["problems"])


def test_a_log_missing_only_its_closing_magic_is_complete_for_info_and_recover(
    whole, tmp_path, capsys
):
    cut = tmp_path / "m1.mcap"
    cut.write_bytes(whole.read_bytes()[:-1])
    assert main(["info", str(cut), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert not info["truncated"] and info["ticks"] == TICKS
    result = recover(cut, tmp_path / "rec.mcap")
    assert result.finished and result.lost_bytes == 0 and "magic" in result.line()


@pytest.mark.parametrize("kind", ["fifo", "chardev"])
def test_recover_refuses_an_out_that_is_not_a_regular_file(whole, tmp_path, capsys, kind):
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    node = tmp_path / "node"
    if kind == "fifo":
        os.mkfifo(node)
    else:
        try:
            os.mknod(node, stat.S_IFCHR | 0o666, os.makedev(1, 3))  # a /dev/null, in tmp_path
        except PermissionError:
            pytest.skip("mknod needs root")
    mode = node.stat().st_mode
    assert main(["recover", str(cut), "--out", str(node)]) == 2
    err = capsys.readouterr().err.strip()
    assert "not a regular file" in err and "\n" not in err
    assert node.stat().st_mode == mode and not stat.S_ISREG(node.stat().st_mode)


def test_replay_refuses_an_out_hard_linked_to_its_input(tmp_path, capsys):
    log = record_run(tmp_path / "run.mcap", RigConfig())
    link = tmp_path / "hard.mcap"
    os.link(log, link)
    before = log.read_bytes()
    assert main(["replay", str(log), "--out", str(link)]) == 2
    assert "overwrite" in capsys.readouterr().err and log.read_bytes() == before


def test_export_refuses_a_log_without_readable_cycles(whole, tmp_path, capsys):
    one = record(tmp_path / "one.mcap", 50, chunk=10**7)  # one chunk, corrupted
    cut = tmp_path / "bad.mcap"
    _corrupt_middle_chunk(one, cut)
    out = tmp_path / "csv"
    assert main(["export", str(cut), "--format", "csv", "--out", str(out)]) == 2
    assert "nothing to export" in capsys.readouterr().err
    assert not out.exists() or not any(out.iterdir())


def test_report_of_several_logs_reports_the_readable_ones(whole, tmp_path, capsys):
    text = tmp_path / "text.mcap"
    text.write_text("not a log\n")
    assert main(["report", "-q", "--json", str(whole), str(text), str(whole)]) == 2
    captured = capsys.readouterr()
    assert len(json.loads(captured.out)) == 2
    assert "text.mcap: not an MCAP file" in captured.err
