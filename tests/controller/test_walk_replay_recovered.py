"""``hil replay`` off its happy path: a log ``hil recover`` made of a cut or damaged one is as
partial as its input (it must not replay as a clean success), and the failure line of a log
with a damaged chunk in the middle does not claim that the "first" ticks were replayed."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hal.config import RigConfig
from rt_controller.cli import main
from rt_controller.logtools.recover import recover
from tests.controller.test_replay import TICKS, record_run
from tests.support.mcap_damage import chunk_starts, damaged_copy


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    return record_run(tmp_path_factory.mktemp("walk") / "run.mcap", RigConfig())


def test_a_recovered_copy_of_a_cut_log_is_still_partial(log, tmp_path, capsys):
    """The cut log fails without --allow-partial; its recovered copy must fail the same way
    (the ticks after the cut are as lost), naming the recovery, and pass with the flag."""
    data = log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    copy = tmp_path / "copy.mcap"
    recover(cut, copy)
    assert main(["replay", str(copy), "--json", "-q"]) == 1
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    assert out["truncated"] is True and out["ok"] is False and out["ticks"] < TICKS
    assert "hil recover" in captured.err and str(cut) in captured.err
    assert "--allow-partial" in captured.err
    assert main(["replay", str(copy), "--json", "-q", "--allow-partial"]) == 0
    capsys.readouterr()


def test_a_recovered_copy_of_a_whole_log_replays_clean(log, tmp_path, capsys):
    """A copy of a finished log lost nothing: it replays as a success."""
    copy = tmp_path / "copy.mcap"
    recover(log, copy)
    assert main(["replay", str(copy), "--json", "-q"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["truncated"] is False and out["ok"] is True and out["ticks"] == TICKS


def test_a_damaged_chunk_in_the_middle_is_not_called_the_first_ticks(log, tmp_path, capsys):
    """Ticks after a skipped chunk are replayed too: the line must not say "its first N"."""
    starts = chunk_starts(log)
    bad = damaged_copy(log, tmp_path, starts[len(starts) // 2] + 200, 64)  # in its data
    assert main(["replay", str(bad), "--json", "-q"]) == 1
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    assert any("damaged chunk" in n for n in out["notes"]), out["notes"]
    assert "only its first" not in captured.err
    assert f"the {out['ticks']} ticks it holds" in captured.err


def test_a_garbage_record_length_in_the_middle_is_damage_not_a_cut(log, tmp_path, capsys):
    """A chunk whose length field is flipped to run past the end of a file that has its
    footer and chunk index: the later chunks are still read (not "cut, the writer did not
    finish it", losing every tick after it)."""
    starts = chunk_starts(log)
    bad = damaged_copy(log, tmp_path, starts[1] + 5, 2)  # a high byte of the record length
    assert main(["replay", str(bad), "--json", "-q", "--allow-partial"]) == 0
    out = json.loads(capsys.readouterr().out)
    notes = " ".join(out["notes"])
    assert "did not finish" not in notes and "damaged chunk" in notes, notes
    whole = main(["replay", str(log), "--json", "-q"])
    assert whole == 0
    ticks = json.loads(capsys.readouterr().out)["ticks"]
    assert ticks - out["ticks"] < ticks // len(starts) + 2  # only one chunk's ticks lost


def test_a_log_cut_before_its_first_cycle_says_it_is_cut(log, tmp_path, capsys):
    """A copy cut inside its first chunk holds no cycle: the error says the file is cut (and
    where), not only that there are no cycle records, as `hil export` does."""
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(log.read_bytes()[: chunk_starts(log)[0] + 100])
    assert main(["replay", str(cut), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(cut) in err and "no /controller/cycle records" in err
    assert "cut at byte" in err, err


def test_republish_of_a_log_cut_before_any_input_blames_the_cut(log, tmp_path):
    """A log cut inside its first chunk holds no raw inputs because it is cut, not because
    it was recorded with --no-raw: the note must say so."""
    from rt_controller.logtools.republish import republish_log

    cut = tmp_path / "cut.mcap"
    cut.write_bytes(log.read_bytes()[: chunk_starts(log)[0] + 100])
    result = republish_log(cut, can_spec="virtual", zenoh_endpoint="tcp/127.0.0.1:1")
    assert result.truncated and result.can_frames == 0 and result.payloads == 0
    last = result.notes[-1]
    assert "--no-raw" not in last and "cut or damaged" in last, result.notes


def test_the_out_log_of_a_partial_replay_is_partial_too(log, tmp_path, capsys):
    """``--allow-partial --out NEW`` on a cut log: NEW holds only the ticks the cut log held,
    so replaying NEW is partial as well (not a clean success that hides the lost ticks)."""
    data = log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    new = tmp_path / "new.mcap"
    assert main(["replay", str(cut), "-q", "--allow-partial", "--out", str(new)]) == 0
    capsys.readouterr()
    assert main(["replay", str(new), "-q", "--json"]) == 1
    captured = capsys.readouterr()
    assert json.loads(captured.out)["truncated"] is True
    assert str(cut) in captured.err and "--allow-partial" in captured.err
    whole = tmp_path / "whole.mcap"
    assert main(["replay", str(log), "-q", "--out", str(whole)]) == 0
    assert main(["replay", str(whole), "-q"]) == 0  # a whole log's replay is whole


def test_a_log_cut_in_its_summary_section_replays_whole(log, tmp_path, capsys):
    """Cut after its data end record (in the summary section): every tick is there, as `hil
    recover` says ("all data kept"), so the replay is whole, with a note, not a failure."""
    data = log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:-40])  # the footer and closing magic gone, the data end kept
    assert recover(cut, tmp_path / "copy.mcap").stopped.endswith("(all data kept)")
    assert main(["replay", str(cut), "--json", "-q"]) == 0, capsys.readouterr().err
    out = json.loads(capsys.readouterr().out)
    assert out["ticks"] == TICKS and out["truncated"] is False
    assert any("summary section" in n for n in out["notes"]), out["notes"]


@pytest.mark.parametrize("command", ["replay", "recover"])
def test_an_out_ending_in_a_slash_is_refused_not_written_as_a_file(log, tmp_path, capsys, command):
    """``--out new/`` says a folder: writing a file named ``new`` is not what was asked; the
    command refuses it (exit 2, one line naming the option) and writes nothing."""
    folder = tmp_path / "new"
    assert (
        main([command, str(log), "-q" if command == "replay" else "--json", "--out", f"{folder}/"])
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--out" in err and f"{folder}/" in err, err
    assert not folder.exists()


def test_a_recovered_copy_of_a_log_with_a_damaged_chunk_is_partial(log, tmp_path, capsys):
    """The input had its footer but a damaged chunk was skipped: the copy lost those ticks."""
    starts = chunk_starts(log)
    bad = damaged_copy(log, tmp_path, starts[len(starts) // 2] + 200, 64)
    copy = tmp_path / "copy.mcap"
    assert recover(bad, copy).skipped
    assert main(["replay", str(copy), "-q"]) == 1
    err = capsys.readouterr().err
    assert "damaged chunks skipped" in err and str(bad) in err, err
