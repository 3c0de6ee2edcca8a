"""Damage in a finished log (footer and summary intact) that the log tools must not call a log
the writer did not finish: byte flips in its last chunk are a damaged chunk (the records after
it, the recorder's closing metadata and the footer, are still read), and damage confined to a
chunk's message indexes (redundant with the chunk) loses no record: a note, not a partial log.
Also: ``hil export --out X.CSV`` names a file whatever the case of its suffix."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hal.config import RigConfig
from rt_controller.cli import main
from tests.controller.test_logs import record
from tests.controller.test_replay import TICKS as RUN_TICKS
from tests.controller.test_replay import record_run
from tests.support.mcap_damage import chunk_indexes, damaged_copy, message_index_starts

TICKS = 400


@pytest.fixture(scope="module")
def whole(tmp_path_factory) -> Path:
    """A finished log of many small chunks."""
    return record(tmp_path_factory.mktemp("index") / "whole.mcap", TICKS, chunk=2048)


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """A finished log of a closed-loop run, which replays exactly."""
    return record_run(tmp_path_factory.mktemp("index-run") / "run.mcap", RigConfig())


def _info(path: Path, capsys) -> dict:
    assert main(["info", str(path), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_a_flip_in_the_last_chunk_of_a_finished_log_is_damage_not_unfinished(
    whole, tmp_path, capsys
):
    last = chunk_indexes(whole)[-1]
    bad = damaged_copy(whole, tmp_path, last.chunk_start_offset + last.chunk_length // 2, 4)
    info = _info(bad, capsys)
    words = " ".join(info["problems"] + info["notes"])
    assert info["damaged"], words
    assert "did not finish" not in words and "did not close" not in words, words
    assert "damaged chunk" in words and 0 < info["ticks"] <= TICKS
    assert main(["info", str(bad)]) == 0
    text = capsys.readouterr().out
    assert "TRUNCATED" not in text and "DAMAGED" in text
    assert main(["report", str(bad)]) in (0, 1)
    text = capsys.readouterr().out
    assert "did not finish" not in text and "did not close" not in text, text


@pytest.mark.parametrize(
    "where",
    [6, 12],  # a high byte of the record's length; its entry array's byte length
    ids=["record-length", "array-length"],
)
def test_damage_only_in_a_message_index_loses_no_record(run, tmp_path, capsys, where):
    starts = message_index_starts(run)
    bad = damaged_copy(run, tmp_path, starts[len(starts) // 2] + where, 1)
    info = _info(bad, capsys)
    assert info["ticks"] == RUN_TICKS and not info["truncated"] and not info["damaged"], info
    assert not any("damaged chunk" in p for p in info["problems"]), info["problems"]
    assert any("message index" in n for n in info["notes"]), info["notes"]
    assert main(["replay", str(bad), "--json", "-q"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["ticks"] == RUN_TICKS and out["truncated"] is False


@pytest.mark.parametrize("name", ["X.CSV", "x.Csv"])
def test_export_out_with_an_upper_case_suffix_is_a_file(whole, tmp_path, capsys, name):
    out = tmp_path / name
    args = ["export", str(whole), "--format", "csv", "--topics", "cycle", "--out", str(out)]
    assert main(args) == 0
    assert out.is_file()
    capsys.readouterr()
    several = tmp_path / ("two" + name)
    assert main(["export", str(whole), "--format", "csv", "--out", str(several)]) == 2
    assert "holds one topic" in capsys.readouterr().err and not several.exists()


def test_export_refuses_an_upper_case_suffix_of_another_format(whole, tmp_path, capsys):
    out = tmp_path / "m.CSV"
    assert main(["export", str(whole), "--format", "mat", "--out", str(out)]) == 2
    assert "names a .csv file" in capsys.readouterr().err.lower() and not out.exists()
