"""A controller told to stop before its first tick still ends its log in order: the final
``/diagnostics`` record (``end_reason``, ``planned_ticks``, the counters) is written, so
``hil info`` says the run was stopped, not that the controller or its recorder was killed."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from hal.bus import isolated_spec
from hal.config import RigConfig, load_config
from hal.errors import HalTransportError
from hal.joint_client import JointClient
from hal.signals import wait_for_stop
from rt_controller.runtime.daemon import ControllerDaemon, DaemonOptions
from tests.controller.test_daemon_fake_clock import NoZenoh


@pytest.fixture(scope="module")
def cfg() -> RigConfig:
    return load_config()


def info_of(log: Path) -> dict:
    """``hil info --json`` of ``log``, through the command line."""
    cmd = [sys.executable, "-m", "rt_controller.cli", "info", "--json", str(log)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode in (0, 1), done.stderr
    return json.loads(done.stdout)


def stopped_before_run(tmp_path: Path, cfg: RigConfig, links: bool) -> tuple[dict, Path]:
    """A daemon whose stop is set before it starts: on given links (no DSP on the bus: it
    stops while waiting for the DSP) or on its own (it stops while waiting for zenoh)."""
    spec = isolated_spec("virtual")
    cfg = cfg.with_overrides({"transport.can": spec, "transport.zenoh_endpoint": "tcp/127.0.0.1:9"})
    log = tmp_path / "early.mcap"
    opts = DaemonOptions(
        duration_s=2.0, log_path=log, realtime_settings=False, live=False, scene=False
    )
    stop = threading.Event()
    stop.set()
    daemon = ControllerDaemon(cfg, opts, stop)
    if not links:
        return daemon.run(), log
    with JointClient.open(spec, cfg) as can:
        return daemon.run((can, NoZenoh())), log


@pytest.mark.parametrize("links", [True, False], ids=["waiting-for-the-dsp", "waiting-for-zenoh"])
def test_a_stop_before_the_first_tick_is_told_as_a_stop(tmp_path, cfg, links):
    summary, log = stopped_before_run(tmp_path, cfg, links)
    assert summary["end_reason"] == "stopped" and summary["ticks"] == 0
    info = info_of(log)
    said = " ".join(info.get("problems", []) + info.get("notes", []))
    assert "killed" not in said and "no final /diagnostics" not in said
    assert info["end_reason"] == "stopped"
    assert info["planned_ticks"] == 100 and info["ticks_run"] == 0


def test_the_stop_event_keeps_which_signal_set_it():
    from hal.signals import signal_name_of, stop_on_signals

    with stop_on_signals() as stop:
        assert signal_name_of(stop) is None
        os.kill(os.getpid(), signal.SIGTERM)
        assert wait_for_stop(stop, timeout_s=10)
        os.kill(os.getpid(), signal.SIGINT)  # a second signal does not rename the first
        time.sleep(0.05)
    assert signal_name_of(stop) == "SIGTERM"
    given = threading.Event()  # a caller's own event keeps it too
    with stop_on_signals(given):
        os.kill(os.getpid(), signal.SIGINT)
        assert wait_for_stop(given, timeout_s=10)
    assert signal_name_of(given) == "SIGINT"
    plain = threading.Event()
    plain.set()
    assert signal_name_of(plain) is None


def test_the_controllers_summary_names_the_stop_signal(tmp_path, cfg):
    from hal.signals import stop_on_signals

    spec = isolated_spec("virtual")
    cfg = cfg.with_overrides({"transport.can": spec})
    opts = DaemonOptions(
        duration_s=2.0,
        log_path=tmp_path / "sig.mcap",
        realtime_settings=False,
        live=False,
        scene=False,
    )
    with stop_on_signals() as stop, JointClient.open(spec, cfg) as can:
        os.kill(os.getpid(), signal.SIGTERM)
        assert wait_for_stop(stop, timeout_s=10)
        summary = ControllerDaemon(cfg, opts, stop).run((can, NoZenoh()))
    assert summary["end_reason"] == "stopped" and summary["stop_signal"] == "SIGTERM"


class RefusingZenoh(NoZenoh):
    """A session on which the ``hil param`` queryable cannot be declared (start-up fails)."""

    class _Session:
        def declare_queryable(self, key: str, on_query: object) -> None:
            raise HalTransportError("zenoh refused the queryable")

    session = _Session()


def test_a_start_that_fails_is_told_as_a_failure_in_the_log(tmp_path, cfg):
    spec = isolated_spec("virtual")
    cfg = cfg.with_overrides({"transport.can": spec})
    log = tmp_path / "failed.mcap"
    opts = DaemonOptions(
        duration_s=2.0, log_path=log, realtime_settings=False, live=False, scene=False
    )
    daemon = ControllerDaemon(cfg, opts, threading.Event())
    with JointClient.open(spec, cfg) as can, pytest.raises(HalTransportError):
        daemon.run((can, RefusingZenoh()))
    info = info_of(log)
    said = " ".join(info.get("problems", []) + info.get("notes", []))
    assert "killed" not in said and "no final /diagnostics" not in said
    assert info["end_reason"] == "failed to start: zenoh refused the queryable"
    assert "the run ended after 0 of 100 ticks: failed to start" in said
