"""The log tools never call a damaged or short log clean: ``hil replay`` counts the cycle records
it could not read and fails without ``--allow-partial``; its ``within_spread`` is null when no
cross-target spread was measured (not a failure read into a clean match); ``hil info`` counts
cycle records without the hil fields as rejected, and reports a run that its final
``/diagnostics`` record says ended early, with the figures (an older log without those fields
is not blamed for lacking them).

The damaged logs are copies of whole ones made with the ``mcap`` library's reader and writer,
one payload changed at a time.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from hal.config import RigConfig
from rt_controller.cli import main
from rt_controller.runtime.counters import run_problems, run_warnings
from rt_controller.runtime.recorder import CYCLE_TOPIC, DIAGNOSTICS_TOPIC
from tests.controller.test_logs import record
from tests.controller.test_replay import TICKS, record_run

Payload = Callable[[int, bytes], bytes]
"""The new payload of the i-th message of a topic, from its old one."""


def rewrite(src: Path, dst: Path, topic: str, payload: Payload) -> Path:
    """A copy of ``src`` as ``dst`` with each message on ``topic`` given ``payload(i, data)``."""
    with src.open("rb") as fh, dst.open("wb") as out:
        reader, writer = make_reader(fh), Writer(out)
        header, summary = reader.get_header(), reader.get_summary()
        writer.start(profile=header.profile, library=header.library)
        schemas = {
            s.id: writer.register_schema(s.name, s.encoding, s.data)
            for s in summary.schemas.values()
        }
        channels = {
            c.id: writer.register_channel(
                c.topic, c.message_encoding, schemas.get(c.schema_id, 0), c.metadata
            )
            for c in summary.channels.values()
        }
        for meta in reader.iter_metadata():
            writer.add_metadata(meta.name, meta.metadata)
        i = 0
        for _, channel, msg in reader.iter_messages(log_time_order=False):
            data = msg.data
            if channel.topic == topic:
                data, i = payload(i, data), i + 1
            writer.add_message(
                channels[channel.id],
                log_time=msg.log_time,
                publish_time=msg.publish_time,
                data=data,
                sequence=msg.sequence,
            )
        writer.finish()
    return dst


def garble_every_tenth(i: int, data: bytes) -> bytes:
    return b"{garbled" if i % 10 == 3 else data


@pytest.fixture(scope="module")
def replayable(tmp_path_factory) -> Path:
    return record_run(tmp_path_factory.mktemp("truth") / "run.mcap", RigConfig())


# ------------------------------------------------------------------------------- hil replay


def test_replay_of_a_log_with_garbled_cycle_records_fails_unless_partial(
    replayable, tmp_path, capsys
):
    bad = rewrite(replayable, tmp_path / "garbled.mcap", CYCLE_TOPIC, garble_every_tenth)
    skipped = TICKS // 10
    assert main(["replay", str(bad), "--json"]) == 1
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    assert out["ok"] is False and out["matches"] is True and out["truncated"] is False
    assert out["skipped_records"] == skipped and out["ticks"] == TICKS - skipped
    line = captured.err.strip()
    assert "\n" not in line and line.startswith("hil replay: log is incomplete or damaged: ")
    assert f"{skipped} cycle record(s) could not be read" in line and "--allow-partial" in line
    assert main(["replay", str(bad)]) == 1
    rows = [r for r in capsys.readouterr().out.splitlines() if "skipped_records" in r]
    assert len(rows) == 1 and f" {skipped} " in rows[0]
    assert main(["replay", str(bad), "--json", "--allow-partial"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["ok"] is True and out["skipped_records"] == skipped


def test_replay_of_a_log_without_cycle_records_names_the_skipped_ones(replayable, tmp_path, capsys):
    alien = rewrite(replayable, tmp_path / "alien.mcap", CYCLE_TOPIC, lambda i, d: b'{"a": 1}')
    assert main(["replay", str(alien)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and f"no /controller/cycle records ({TICKS} unreadable" in err


def test_within_spread_does_not_apply_to_a_clean_match(replayable, capsys):
    """No cross-target spread is measured when the replay matches: ``within_spread`` is null
    like ``cross_target_spread``, never a False beside ``ok`` True."""
    assert main(["replay", str(replayable), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["ok"] is True and out["matches"] is True and out["skipped_records"] == 0
    assert out["cross_target_spread"] is None and out["within_spread"] is None
    assert main(["replay", str(replayable)]) == 0
    rows = [r for r in capsys.readouterr().out.splitlines() if "within_spread" in r]
    assert len(rows) == 1 and "False" not in rows[0]


# --------------------------------------------------------------------------------- hil info


def info_of(path: Path, capsys) -> dict:
    assert main(["info", str(path), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize(
    ("payload", "why"),
    [
        (lambda i, d: b'{"a": 1}', "JSON objects without an integer tick"),
        (lambda i, d: b'{"tick": "7"}', "JSON objects without an integer tick"),
        (lambda i, d: b"\xff not JSON", "not valid JSON objects"),
    ],
    ids=["no-hil-fields", "tick-not-integer", "not-json"],
)
def test_info_counts_cycle_records_it_cannot_read_as_rejected(tmp_path, capsys, payload, why):
    whole = record(tmp_path / "whole.mcap", 40)
    bad = rewrite(whole, tmp_path / "bad.mcap", CYCLE_TOPIC, payload)
    info = info_of(bad, capsys)
    assert info["ticks"] == 0 and info["topics"][CYCLE_TOPIC]["messages"] == 40
    assert info["rejected"] == {CYCLE_TOPIC: 40}
    assert f"40 {CYCLE_TOPIC} message(s) could not be read as records" in info["problems"][-1]
    notes = " ".join(info["notes"])
    assert f"40 {CYCLE_TOPIC} message(s) were {why}" in notes
    assert "no /controller/cycle messages in the log" not in notes
    assert f"none of the 40 {CYCLE_TOPIC} message(s) in the log is a readable" in notes
    assert main(["info", str(bad)]) == 0
    text = capsys.readouterr().out
    assert "problems:        none" not in text and "40 /controller/cycle message(s)" in text


def test_info_of_a_log_with_some_garbled_cycle_records_is_not_clean(tmp_path, capsys):
    whole = record(tmp_path / "whole.mcap", 40)
    bad = rewrite(whole, tmp_path / "bad.mcap", CYCLE_TOPIC, garble_every_tenth)
    info = info_of(bad, capsys)
    assert info["ticks"] == 36 and info["rejected"] == {CYCLE_TOPIC: 4}
    assert info["problems"] == [
        f"4 {CYCLE_TOPIC} message(s) could not be read as records and were skipped"
    ]


def with_end(planned: int | None, reason: str) -> Payload:
    """The final /diagnostics record given ``planned_ticks`` and ``end_reason``, as the
    daemon writes them (:func:`rt_controller.runtime.diagnostics.with_run_end`)."""

    def payload(i: int, data: bytes) -> bytes:
        rec = json.loads(data)
        if not rec.get("final"):
            return data
        return json.dumps({**rec, "planned_ticks": planned, "end_reason": reason}).encode()

    return payload


STOPPED_SHORT = "the run ended after 60 of 250 ticks: stopped"


@pytest.mark.parametrize(
    ("planned", "reason", "problem", "warning"),
    [
        (250, "stopped", None, STOPPED_SHORT),  # asked for: clean, its J of fewer ticks
        (
            250,
            "no Sync from the DSP for 2 s",
            "the run ended after 60 of 250 ticks: no Sync ",
            None,
        ),
        (250, "duration", None, None),  # fewer ticks: periods missed in realtime are skipped
        (None, "no Sync from the DSP for 2 s", "the run ended after 60 ticks: no Sync from ", None),
        (60, "duration", None, None),
        (60, "stopped", None, None),
        (None, "stopped", None, None),
    ],
)
def test_info_judges_how_a_run_ended_as_its_summary_did(
    tmp_path, capsys, planned, reason, problem, warning
):
    """The controller's own rule: a failure is a problem, a stop before the duration a
    warning; the same verdict as the summary the controller printed."""
    whole = record(tmp_path / "whole.mcap", 60)  # its final record: 60 ticks ran
    cut = rewrite(whole, tmp_path / "cut.mcap", DIAGNOSTICS_TOPIC, with_end(planned, reason))
    info = info_of(cut, capsys)
    assert (info["planned_ticks"], info["end_reason"], info["ticks_run"]) == (
        planned,
        reason,
        60,
    )
    if problem is None:
        assert info["problems"] == []
    else:
        assert len(info["problems"]) == 1 and info["problems"][0].startswith(problem)
    assert info["warnings"] == ([] if warning is None else [warning])
    summary = {"planned_ticks": planned, "end_reason": reason, "ticks": 60}
    assert run_problems(summary) == info["problems"]
    assert run_warnings(summary) == info["warnings"]
    assert main(["info", str(cut)]) == 0
    text = capsys.readouterr().out
    of = f" of {planned} planned" if planned is not None else ""
    assert f"ended:           {reason}, after 60{of} ticks" in text


def test_info_of_a_log_without_the_end_fields_is_not_blamed_for_it(tmp_path, capsys):
    """A log of a controller before the final record had ``planned_ticks`` and ``end_reason``:
    no problem for their absence, nulls in --json, no ``ended`` line."""
    info = info_of(record(tmp_path / "old.mcap", 60), capsys)
    assert info["problems"] == [] and info["rejected"] == {}
    assert (info["planned_ticks"], info["end_reason"], info["ticks_run"]) == (None, None, None)
    assert main(["info", str(tmp_path / "old.mcap")]) == 0
    assert "ended:" not in capsys.readouterr().out
