"""What became of a run's tuning requests and what stopped it reach every reader of the run: a
parameter request the controller failed on is a warning of the run (``hil up``, ``hil info``,
``hil report``), ``hil report`` counts it beside the others, and a log says which signal
stopped its controller as ``hil up`` does."""

from __future__ import annotations

import contextlib
import json
import os
import signal
from pathlib import Path

import pytest

from hal.config import load_config
from hal.signals import stop_on_signals
from rt_controller.cli import main
from rt_controller.runtime.counters import run_warnings
from rt_controller.runtime.recorder import DIAGNOSTICS_TOPIC
from tests.controller import test_daemon_fake_clock as fake
from tests.controller.test_log_truth import rewrite

COUNTS = {"accepted": 2, "refused": 1, "unauthenticated": 3, "failed": 1}
FAILED = "1 parameter request(s) failed in the controller"


def test_a_run_whose_tuning_request_failed_warns_of_it():
    counts = {"accepted": 0, "refused": 0, "unauthenticated": 0, "failed": 2}
    warnings = run_warnings({"parameters": counts})
    assert [w for w in warnings if "2 parameter request(s) failed in the controller" in w]
    assert run_warnings({"parameters": {**counts, "failed": 0}}) == []


def with_counts(_i: int, data: bytes) -> bytes:
    """The final record with the parameter service's :data:`COUNTS`."""
    rec = json.loads(data)
    if rec.get("final"):
        for status in rec["status"]:
            if status["name"] == "parameters":
                status["values"] = dict(COUNTS)
    return json.dumps(rec).encode()


@pytest.fixture(scope="module")
def failed_request_log(tmp_path_factory) -> Path:
    """A short run's log whose final record counts a request the controller failed on."""
    tmp = tmp_path_factory.mktemp("failed-request")
    summary, _, _ = fake.run_daemon(tmp, load_config(), 0.5, {})
    return rewrite(Path(summary["log"]), tmp / "failed.mcap", DIAGNOSTICS_TOPIC, with_counts)


def test_hil_info_warns_of_a_failed_parameter_request(failed_request_log, capsys):
    assert main(["info", str(failed_request_log), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert [w for w in info["warnings"] if FAILED in w], info["warnings"]
    assert main(["info", str(failed_request_log)]) == 0
    assert FAILED in capsys.readouterr().out


def test_hil_report_counts_the_failed_parameter_requests(failed_request_log, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "200")  # rich: one table row a line
    assert main(["report", str(failed_request_log)]) == 0
    lines = capsys.readouterr().out.splitlines()
    row = [line for line in lines if "parameter requests" in line]
    assert len(row) == 1, lines
    assert "accepted / refused / unauthenticated / failed" in row[0]
    assert row[0].rstrip(" │").endswith("2 / 1 / 3 / 1")
    assert main(["report", str(failed_request_log), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert [w for w in rep["warnings"] if FAILED in w], rep["warnings"]


@pytest.fixture(scope="module")
def sigint_log(tmp_path_factory) -> tuple[dict, Path]:
    """(summary, log) of a run a SIGINT stopped at about tick 10 of 25."""
    tmp = tmp_path_factory.mktemp("sigint")
    with contextlib.ExitStack() as signals:

        def on_start(daemon) -> None:
            signals.enter_context(stop_on_signals(daemon.stop))

        def on_tick(tick: int, _node) -> None:
            if tick == 10:
                os.kill(os.getpid(), signal.SIGINT)

        summary, _, _ = fake.run_daemon(
            tmp, load_config(), 0.5, {}, on_tick=on_tick, on_start=on_start
        )
    return summary, Path(summary["log"])


def test_hil_info_names_the_signal_that_stopped_the_run(sigint_log, capsys):
    summary, log = sigint_log
    assert (summary["end_reason"], summary["stop_signal"]) == ("stopped", "SIGINT")
    assert main(["info", str(log), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert (info["end_reason"], info["stop_signal"]) == ("stopped", "SIGINT")
    assert main(["info", str(log)]) == 0
    ended = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("ended:")]
    assert len(ended) == 1 and ended[0].split(":", 1)[1].strip().startswith("stopped by SIGINT")


def test_hil_info_of_a_whole_run_names_no_signal(failed_request_log, capsys):
    assert main(["info", str(failed_request_log), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert (info["end_reason"], info["stop_signal"]) == ("duration", None)
