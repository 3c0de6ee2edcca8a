"""``hil recover`` of a log with nothing left to recover (cut or damaged inside its first and
only chunk) writes no empty copy; ``hil info`` of a copy that lost records says it is partial.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from hal.config import RigConfig
from rt_controller.cli import main
from rt_controller.runtime.recorder import CycleRecorder
from tests.controller.test_replay import record_run
from tests.support.mcap_damage import chunk_indexes, damaged_copy


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    return record_run(tmp_path_factory.mktemp("walk_logs") / "run.mcap", RigConfig())


@pytest.fixture(scope="module")
def one_chunk(tmp_path_factory) -> Path:
    """A log whose messages are all in one chunk, as a short lockstep run writes it."""
    import can

    path = tmp_path_factory.mktemp("one_chunk") / "run.mcap"
    with CycleRecorder(path, RigConfig(), run_info={"clock": "lockstep"}) as rec:
        for k in range(2000):
            msg = can.Message(arbitration_id=0x10, data=os.urandom(8))
            rec.record_can(msg, 1_000_000 + k * 1000, "rx")
    assert len(chunk_indexes(path)) == 1
    return path


def nothing_recovered(capsys, bad: Path, out: Path) -> str:
    assert main(["recover", str(bad), "--out", str(out)]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith(f"hil recover: error: {bad}: nothing to recover"), lines
    assert not out.exists()
    assert not [p for p in out.parent.iterdir() if p.name.endswith(".partial")]
    return lines[0]


def test_a_log_cut_inside_its_only_chunk_has_nothing_to_recover(one_chunk, tmp_path, capsys):
    chunk = chunk_indexes(one_chunk)[0]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(one_chunk.read_bytes()[: chunk.chunk_start_offset + chunk.chunk_length // 2])
    line = nothing_recovered(capsys, cut, tmp_path / "copy.mcap")
    assert f"byte {chunk.chunk_start_offset}" in line  # where the unreadable record starts
    assert cut.stat().st_size == chunk.chunk_start_offset + chunk.chunk_length // 2


def test_a_log_damaged_inside_its_only_chunk_has_nothing_to_recover(one_chunk, tmp_path, capsys):
    chunk = chunk_indexes(one_chunk)[0]
    bad = damaged_copy(one_chunk, tmp_path, chunk.chunk_start_offset + chunk.chunk_length // 2, 1)
    line = nothing_recovered(capsys, bad, tmp_path / "copy.mcap")
    assert f"byte {chunk.chunk_start_offset}" in line and "damaged" in line


def test_a_log_cut_after_its_chunk_is_still_recovered(one_chunk, tmp_path, capsys):
    """The rule is about messages kept, not about the chunk count."""
    chunk = chunk_indexes(one_chunk)[0]
    cut = tmp_path / "cut.mcap"
    end = chunk.chunk_start_offset + chunk.chunk_length
    cut.write_bytes(one_chunk.read_bytes()[:end])
    assert main(["recover", str(cut), "--out", str(tmp_path / "copy.mcap"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["messages"] == 2000


def info_of(capsys, path: Path) -> tuple[str, dict]:
    assert main(["info", str(path)]) == 0
    text = capsys.readouterr().out
    assert main(["info", str(path), "--json"]) == 0
    return text, json.loads(capsys.readouterr().out)


def state_line(text: str) -> str:
    return next(line for line in text.splitlines() if line.startswith("state:"))


def test_info_of_a_copy_of_a_log_with_its_last_chunk_damaged_is_partial(log, tmp_path, capsys):
    last = chunk_indexes(log)[-1]
    bad = damaged_copy(log, tmp_path, last.chunk_start_offset + last.chunk_length // 2, 1)
    copy = tmp_path / "copy.mcap"
    assert main(["recover", str(bad), "--out", str(copy)]) == 0
    capsys.readouterr()
    text, info = info_of(capsys, copy)
    state = state_line(text)
    assert "complete" not in state and "PARTIAL" in state, state
    assert "hil recover" in state and str(bad) in state
    assert info["recovered"]["skipped_bytes"] > 0


def test_info_of_a_copy_of_a_cut_log_is_partial(log, tmp_path, capsys):
    data = log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    copy = tmp_path / "copy.mcap"
    assert main(["recover", str(cut), "--out", str(copy)]) == 0
    capsys.readouterr()
    assert "PARTIAL" in state_line(info_of(capsys, copy)[0])


def test_info_of_a_copy_of_a_whole_log_is_complete(log, tmp_path, capsys):
    copy = tmp_path / "copy.mcap"
    assert main(["recover", str(log), "--out", str(copy)]) == 0
    capsys.readouterr()
    assert state_line(info_of(capsys, copy)[0]).endswith("complete")


def test_info_of_a_replay_of_a_partial_log_is_partial(log, tmp_path, capsys):
    data = log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    out = tmp_path / "replayed.mcap"
    main(["replay", str(cut), "--out", str(out), "--allow-partial", "-q"])
    capsys.readouterr()
    assert out.exists()
    assert "PARTIAL" in state_line(info_of(capsys, out)[0])
