"""A log is judged as its run was: ``hil info`` and ``hil report`` give the problems the
controller's own summary gave (``run_problems``), including those only the loop counts (camera
outages, DSP faults, ticks without an enabled DSP), which the run's final ``/diagnostics``
record carries; a log without them (a killed run, an older log) has its outages rebuilt from
the cycle records. Refused unauthenticated parameter requests are a warning, not a problem.

The runs are the real daemon on the fake clock (:mod:`tests.controller.test_daemon_fake_clock`).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hal.config import RigConfig, load_config
from hal.drive_state import FaultReason
from rt_controller.cli import main
from rt_controller.runtime.recorder import DIAGNOSTICS_TOPIC
from tests.controller import test_daemon_fake_clock as fake
from tests.controller.test_log_truth import rewrite

MS = 1_000_000
OUTAGE_NS = (fake.T0 + 1_000 * MS, fake.T0 + 3_000 * MS)
"""The camera sends nothing from 1 s to 3 s of a 4 s run: half its ticks on stale features."""


@pytest.fixture(scope="module")
def cfg() -> RigConfig:
    return load_config()


def info_of(path: Path, capsys) -> dict:
    assert main(["info", str(path), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def report_of(path: Path, capsys) -> tuple[dict, str]:
    assert main(["report", str(path), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert main(["report", str(path)]) == 0
    return rep, capsys.readouterr().out


@pytest.fixture(scope="module")
def outage_run(tmp_path_factory, cfg):
    """(summary, log) of a 4 s run whose camera is silent for 2 s."""
    feed = fake.RigClock._camera

    def camera(self) -> None:
        if OUTAGE_NS[0] <= self.t < OUTAGE_NS[1]:
            self.frame += 1  # the frame is lost on the way
            self.next_frame += fake.FRAME_NS
            return
        feed(self)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fake.RigClock, "_camera", camera)
        summary, _, _ = fake.run_daemon(tmp_path_factory.mktemp("outage"), cfg, 4.0, {})
    return summary, Path(summary["log"])


@pytest.fixture(scope="module")
def fault_run(tmp_path_factory, cfg):
    """(summary, log) of a 3 s run whose DSP faults (position limit) at tick 50."""

    def on_tick(tick: int, node) -> None:
        if tick == 50:
            node.fault(FaultReason.POSITION_LIMIT, "injected by the test")

    summary, _, _ = fake.run_daemon(tmp_path_factory.mktemp("fault"), cfg, 3.0, {}, on_tick=on_tick)
    return summary, Path(summary["log"])


def test_info_and_report_judge_a_camera_outage_as_the_controller_did(outage_run, capsys):
    summary, log = outage_run
    assert any("outage_max_share" in p for p in summary["problems"]), summary["problems"]
    assert info_of(log, capsys)["problems"] == summary["problems"]
    rep, text = report_of(log, capsys)
    assert rep["problems"] == summary["problems"]
    assert "run not clean:" in text and "outage_max_share" in text


def test_info_and_report_judge_a_dsp_fault_as_the_controller_did(fault_run, capsys):
    summary, log = fault_run
    problems = summary["problems"]
    assert any(p.startswith("DSP fault(s): position_limit 1") for p in problems), problems
    assert any("without an enabled DSP" in p for p in problems), problems
    assert info_of(log, capsys)["problems"] == problems
    rep, text = report_of(log, capsys)
    assert rep["problems"] == problems
    assert "run not clean:" in text and "DSP fault(s): position_limit 1" in text


def drop_judged(i: int, data: bytes) -> bytes:
    """The final record as an older controller wrote it: without the run's judged counters."""
    rec = json.loads(data)
    for key in ("dsp_faults", "drive_ticks", "outages"):
        rec.pop(key, None)
    return json.dumps(rec).encode()


def test_an_older_log_has_its_outages_rebuilt_from_the_cycle_records(outage_run, tmp_path, capsys):
    summary, log = outage_run
    old = rewrite(log, tmp_path / "old.mcap", DIAGNOSTICS_TOPIC, drop_judged)
    info = info_of(old, capsys)
    assert [p for p in info["problems"] if "outage_max_share" in p] == [
        p for p in summary["problems"] if "outage_max_share" in p
    ]


def test_a_clean_older_log_gets_no_invented_problem(tmp_path, cfg, capsys):
    summary, _, _ = fake.run_daemon(tmp_path, cfg, 1.0, {})
    assert summary["problems"] == []
    old = rewrite(Path(summary["log"]), tmp_path / "old.mcap", DIAGNOSTICS_TOPIC, drop_judged)
    assert info_of(old, capsys)["problems"] == []
    rep, text = report_of(old, capsys)
    assert rep["problems"] == [] and "problems: none" in text


def with_rogue_requests(i: int, data: bytes) -> bytes:
    """The final record of a run that refused 4 unauthenticated `hil param set` requests."""
    rec = json.loads(data)
    if rec.get("final"):
        for status in rec["status"]:
            if status["name"] == "parameters":
                status["values"]["unauthenticated"] = 4
    return json.dumps(rec).encode()


def test_refused_unauthenticated_parameter_requests_are_shown_not_a_problem(tmp_path, cfg, capsys):
    summary, _, _ = fake.run_daemon(tmp_path, cfg, 1.0, {})
    log = rewrite(Path(summary["log"]), tmp_path / "rogue.mcap", DIAGNOSTICS_TOPIC,
                  with_rogue_requests)  # fmt: skip
    info = info_of(log, capsys)
    assert info["problems"] == []
    assert any("4 unauthenticated parameter request(s)" in w for w in info["warnings"])
    assert main(["info", str(log)]) == 0
    assert "4 unauthenticated parameter request(s)" in capsys.readouterr().out
    rep, text = report_of(log, capsys)
    assert rep["diagnostics"]["parameters"]["unauthenticated"] == 4
    assert any("4 unauthenticated parameter request(s)" in w for w in rep["warnings"])
    assert "4 unauthenticated parameter request(s)" in text


def as_a_cia402_log_of_old(i: int, data: bytes) -> bytes:
    """An older log's records without the ``dsp`` component's ``ticks.*`` counts: the shape of
    a cia402 run's (its ``dsp`` block never had them)."""
    rec = json.loads(drop_judged(i, data))
    for status in rec["status"]:
        if status["name"] == "dsp":
            status["values"] = {
                k: v for k, v in status["values"].items() if not k.startswith("ticks.")
            }
    return json.dumps(rec).encode()


def test_ticks_without_an_enabled_dsp_are_rebuilt_from_the_cycle_modes(fault_run, tmp_path, capsys):
    summary, log = fault_run
    old = rewrite(log, tmp_path / "old.mcap", DIAGNOSTICS_TOPIC, as_a_cia402_log_of_old)
    drive = [p for p in summary["problems"] if "without an enabled DSP" in p]
    assert drive and [p for p in info_of(old, capsys)["problems"] if p in drive] == drive
