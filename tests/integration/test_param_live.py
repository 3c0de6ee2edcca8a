"""``hil param`` against a running ``hil up --lockstep``: a kp change at a known tick is in the
log at that tick, changes J and replays exactly; a refused change (alpha not positive definite)
and a client with another rig key change nothing, and the latter is counted in /diagnostics.
Lockstep runs are deterministic, so an untouched run is the reference. Nothing here asserts a
wall-clock timing."""

from __future__ import annotations

import json
import os
import signal
import subprocess
from subprocess import PIPE

import numpy as np
import pytest

from hal.secoc import write_key_file
from rt_controller.logtools.reader import read_log
from rt_controller.logtools.replay import replay_loaded
from tests.support import free_endpoint, hil_command, run_hil, start_hil_up, wait_until

pytestmark = [pytest.mark.integration, pytest.mark.slow]

RUN = ("--lockstep", "--law", "ioc", "--duration", "60", "--json")
REFUSED_AT, CHANGED_AT = 2400, 2500
"""Late enough that the requests (three ``hil param`` processes, started once the controller
answers) arrive before, with seconds to spare on a loaded host: lockstep runs as fast as the
processes allow, about 130-500 ticks/s here."""


def _answers(ep: str) -> bool:
    out = run_hil(["param", "get", "--zenoh-endpoint", ep, "--timeout", "1"], timeout_s=60)
    return out.returncode == 0


def _param(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen([*hil_command(), "param", *args], stdout=PIPE, stderr=PIPE, text=True)


def _done(proc: subprocess.Popen) -> subprocess.CompletedProcess:
    out, err = proc.communicate(timeout=300)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def _finish(proc) -> dict:
    try:
        out, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:  # pragma: no cover - only on a hang
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 0, err
    return json.loads(out)


def test_param_set_at_a_tick_in_a_lockstep_run(tmp_path):
    ep0, ep = free_endpoint(), free_endpoint()
    key = ("--key-file", os.environ["HIL_KEY_FILE"])  # the rig's key is the session's
    base = _finish(start_hil_up(ep0, tmp_path / "base.mcap", *RUN, *key))
    proc = start_hil_up(ep, tmp_path / "tuned.mcap", *RUN, *key)
    try:
        assert wait_until(lambda: _answers(ep), timeout_s=120, poll_s=0.2)
        zen = ["--zenoh-endpoint", ep, "--json"]
        rogue_key = write_key_file(tmp_path / "rogue.key")
        rogue = run_hil(
            ["param", "set", "gains.kp=5", "--key-file", str(rogue_key), "--timeout", "1", *zen],
            timeout_s=60,
        )
        # each answer comes at its tick: the two requests wait side by side
        alpha = "gains.alpha=[[1, 2], [2, 1]]"
        bad_p = _param(["set", alpha, "--at-tick", str(REFUSED_AT), *zen])
        good_p = _param(["set", "gains.kp=0.3", "--at-tick", str(CHANGED_AT), *zen])
        bad, good = (_done(p) for p in (bad_p, good_p))
    except BaseException:
        os.killpg(proc.pid, signal.SIGKILL)
        raise
    tuned = _finish(proc)
    assert bad.returncode == 1 and "gains.alpha" in json.loads(bad.stdout)["reason"]
    assert rogue.returncode == 2 and "no answer" in rogue.stderr
    assert good.returncode == 0, good.stderr
    ack = json.loads(good.stdout)
    assert ack["accepted"] and ack["tick"] == CHANGED_AT and ack["param_set"] == 1

    log0, log = read_log(tmp_path / "base.mcap"), read_log(tmp_path / "tuned.mcap")
    refused, accepted = log.parameters
    assert (refused["tick"], refused["accepted"]) == (REFUSED_AT, False)
    assert "positive definite" in refused["reason"] or "gains.alpha" in refused["reason"]
    assert (accepted["tick"], accepted["accepted"]) == (CHANGED_AT, True)
    assert accepted["changes"] == [{"key": "gains.kp", "old": 0.13, "new": 0.3}]
    ticks = np.asarray(log.cycles["tick"])
    k = int(np.flatnonzero(ticks == CHANGED_AT)[0])
    assert np.array_equal(np.asarray(log.cycles["param_set"])[k - 1 : k + 1], [0, 1])
    u0, u = np.asarray(log0.cycles["u"]), np.asarray(log.cycles["u"])
    assert np.array_equal(u0[:k], u[:k])  # the refusal changed nothing
    assert not np.allclose(u0[k:], u[k:])
    assert tuned["J"] != base["J"]
    result = replay_loaded(log, tol=1e-9)
    assert result.ok, result.failure_line()
    final = log.diagnostics[-1]
    counts = next(s for s in final["status"] if s["name"] == "parameters")["values"]
    assert counts == {"accepted": 1, "refused": 1, "unauthenticated": 1}
