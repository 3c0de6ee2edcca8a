"""``hil up``'s options off the happy path (a user's walk):

* ``--allow-tuning`` without ``--monitor`` has nothing to act on: a usage error (exit 2), not a
  run whose read-only default the user did not ask for;
* a run past its ``--wall-timeout`` is stopped by the rig: its summary says so, not
  "controller exited with status 0" as if it had ended on its own.

The real ``hil up`` runs, on a private CAN bus and zenoh endpoint; no wall-clock assertion.
"""

from __future__ import annotations

import json

import pytest

from hal.bus import isolated_spec
from hal.zenoh_session import free_loopback_port
from tests.support import run_hil

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]


def _private() -> list[str]:
    return [
        "--can",
        isolated_spec("udp_multicast"),
        "--zenoh-endpoint",
        f"tcp/127.0.0.1:{free_loopback_port()}",
    ]


def test_allow_tuning_without_monitor_is_a_usage_error(tmp_path):
    log = tmp_path / "run.mcap"
    args = ["up", "--lockstep", "--duration", "0.2", "--allow-tuning", "--log", str(log)]
    done = run_hil([*args, *_private()], timeout_s=240)
    assert done.returncode == 2, done.stdout + done.stderr
    assert "--allow-tuning" in done.stderr and "--monitor" in done.stderr
    assert "Traceback" not in done.stderr
    assert not log.exists()  # refused before any process started


def test_wall_timeout_end_says_the_rig_stopped_the_controller(tmp_path):
    log = tmp_path / "run.mcap"
    # 0.01 s of wall clock cannot hold the rig's start-up: the budget runs out first
    args = ["up", "--lockstep", "--duration", "1", "--wall-timeout", "0.01", "--json"]
    done = run_hil([*args, "--log", str(log), *_private()], timeout_s=240)
    assert done.returncode == 1, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    summary = json.loads(next(x for x in done.stdout.splitlines() if x.startswith("{")))
    assert "exited with status 0" not in summary["end_reason"], summary["end_reason"]
    assert "wall-clock budget" in summary["end_reason"], summary["end_reason"]
    assert summary["problems"][0].startswith("hung: "), summary["problems"]


def test_monitor_port_0_says_which_port_the_live_view_got(tmp_path):
    args = ["up", "--lockstep", "--duration", "0.5", "--monitor-port", "0", "--json"]
    done = run_hil([*args, "--log", str(tmp_path / "run.mcap"), *_private()], timeout_s=240)
    assert done.returncode == 0, done.stdout + done.stderr
    said = [x for x in done.stderr.splitlines() if "live view on ws://127.0.0.1:" in x]
    assert len(said) == 1, done.stderr
    port = int(said[0].split("ws://127.0.0.1:")[1].split()[0])
    assert 0 < port < 65536
    assert json.loads(done.stdout)["exit_codes"]["monitor"] == 0


def test_a_run_the_budget_cut_short_is_not_warned_as_stopped_by_a_signal(tmp_path):
    """The rig's own stop at the end of its wall-clock budget is the problem (hung), not a
    "stopped by SIGTERM" warning that reads as someone else's signal."""
    args = ["up", "--lockstep", "--duration", "600", "--wall-timeout", "15", "--json"]
    done = run_hil([*args, "--log", str(tmp_path / "run.mcap"), *_private()], timeout_s=240)
    assert done.returncode == 1, done.stdout + done.stderr
    summary = json.loads(next(x for x in done.stdout.splitlines() if x.startswith("{")))
    assert summary["ticks"], summary  # it ran a while: the controller printed its summary
    assert "wall-clock budget" in summary["end_reason"], summary["end_reason"]
    assert not [w for w in summary["warnings"] if "stopped by SIG" in w], summary["warnings"]
