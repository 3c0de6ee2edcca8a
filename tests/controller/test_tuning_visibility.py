"""What became of the run's tuning requests, and what stopped the run, reach the user: a request
the controller failed on is in ``/diagnostics`` (an error there); ``hil info`` shows the
parameter service's counts; ``hil up``'s summary names the signal that stopped the controller.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hal.config import RigConfig, load_config
from rt_controller.calibration.link import ParameterLinkError, ParameterServer, request
from rt_controller.calibration.parameters import ParameterService
from rt_controller.cli import main
from rt_controller.rig import processes
from rt_controller.rig.ending import stopped_from_outside
from rt_controller.runtime import diagnostics
from rt_controller.runtime.recorder import DIAGNOSTICS_TOPIC
from tests.controller import test_daemon_fake_clock as fake
from tests.controller.test_log_truth import rewrite
from tests.controller.test_param_link_failure import KEY, InProcessZenoh

COUNTS = {"accepted": 2, "refused": 1, "unauthenticated": 3, "failed": 1}


def _record(parameters: dict | None) -> dict:
    """A ``/diagnostics`` record of quiet components with the parameter service's counts."""
    return diagnostics.build(
        t_ns=0, tick=0, can_rx={}, features={}, dsp={}, controller={}, recorder={},
        parameters=parameters,
    )  # fmt: skip


def test_requests_the_controller_failed_on_are_an_error_in_diagnostics():
    broken = ParameterService(None)  # type: ignore[arg-type]  # no configuration to read
    ParameterServer(broken, KEY).attach(zenoh := InProcessZenoh())
    for _ in range(2):
        with pytest.raises(ParameterLinkError):
            request(zenoh, KEY, "get")
    record = _record(broken.counters.as_dict())  # as the control loop builds it
    status = next(s for s in record["status"] if s["name"] == "parameters")
    assert status["values"]["failed"] == 2
    assert status["level"] == record["level"] == diagnostics.ERROR
    assert "2 request(s) failed" in status["message"]
    quiet = ParameterService(RigConfig()).counters.as_dict()  # none failed: as before
    assert quiet == {"accepted": 0, "refused": 0, "unauthenticated": 0}
    assert _record(quiet)["level"] == diagnostics.OK


@pytest.fixture(scope="module")
def run_log(tmp_path_factory) -> tuple[Path, Path]:
    """(log, tmp dir) of a short run on the fake clock."""
    tmp = tmp_path_factory.mktemp("tuning")
    summary, _, _ = fake.run_daemon(tmp, load_config(), 0.5, {})
    return Path(summary["log"]), tmp


def _final_parameters(values: dict | None):
    """A rewrite giving the final record's ``parameters`` component ``values`` (None: none)."""

    def payload(_i: int, data: bytes) -> bytes:
        rec = json.loads(data)
        if rec.get("final"):
            rec["status"] = [s for s in rec["status"] if s["name"] != "parameters"]
            if values is not None:
                rec["status"].append({"name": "parameters", "level": 0, "message": "",
                                      "values": values})  # fmt: skip
        return json.dumps(rec).encode()

    return payload


def test_hil_info_shows_the_parameter_requests(run_log, capsys):
    src, tmp = run_log
    log = rewrite(src, tmp / "tuned.mcap", DIAGNOSTICS_TOPIC, _final_parameters(COUNTS))
    assert main(["info", str(log), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["parameters"] == COUNTS
    assert main(["info", str(log)]) == 0
    lines = capsys.readouterr().out.splitlines()
    said = [line for line in lines if line.startswith("parameters:")]
    assert len(said) == 1, lines
    assert said[0].endswith("2 accepted, 1 refused, 3 unauthenticated, 1 failed")


def test_hil_info_of_a_run_without_the_parameter_service_says_nothing_of_it(run_log, capsys):
    src, tmp = run_log
    log = rewrite(src, tmp / "untuned.mcap", DIAGNOSTICS_TOPIC, _final_parameters(None))
    assert main(["info", str(log), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["parameters"] == {}
    assert main(["info", str(log)]) == 0
    assert "\nparameters:" not in capsys.readouterr().out


STOPPED = {"ticks": 12, "planned_ticks": 500, "end_reason": "stopped", "stop_signal": "SIGINT",
           "problems": [], "warnings": []}  # fmt: skip
"""The controller's summary of a run a Ctrl-C stopped."""


def test_hil_up_names_the_signal_that_stopped_the_controller(monkeypatch, capsys):
    monkeypatch.setattr(processes, "run_rig", lambda _opts: dict(STOPPED))
    assert main(["up", "--duration", "10", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["stop_signal"] == "SIGINT"
    assert main(["up", "--duration", "10"]) == 0
    assert "stopped by SIGINT" in capsys.readouterr().out
    said = stopped_from_outside(STOPPED)
    assert said.startswith("the controller was stopped by a signal the rig did not send, ")
    assert said.endswith("after 12 of 500 ticks (SIGINT)")


def test_the_summary_gives_the_law_at_the_end_with_its_settings(tmp_path):
    """A run switched from ioc to rhc (T = 0.2 s, N = 8) on the way: the summary's law is rhc
    and its horizon and steps are the ones that ran, not the start's (ioc: none)."""
    from rt_controller.calibration.parameters import Request

    switch = {"controller.law": "rhc", "rhc.horizon": 0.2, "rhc.steps": 8}
    summary, log, _ = fake.run_daemon(
        tmp_path, load_config(), 0.5, {},
        on_start=lambda daemon: daemon.params.submit(Request(switch, at_tick=10)),
    )  # fmt: skip
    assert set(log.cycles["law"]) == {"ioc", "rhc"}
    assert (summary["law"], summary["horizon_s"], summary["steps"]) == ("rhc", 0.2, 8)
