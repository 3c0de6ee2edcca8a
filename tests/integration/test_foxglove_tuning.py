"""Live calibration from Foxglove: ``hil up --lockstep --monitor --allow-tuning`` with an
independent Foxglove WebSocket client (:mod:`tests.support.foxglove_ws`, written from the
protocol). A ``gains.kp`` set with ``hil.at_tick`` lands at that tick: it is in the log there,
J differs from an untouched run, ``hil replay --tol 1e-9`` is exact and the cycles equal those of
the same change made with ``hil param set``. Without ``--allow-tuning`` the set is refused and
the cycles equal the untouched run's. Lockstep runs are deterministic; no wall-clock
assertion."""

from __future__ import annotations

import json
import os
import signal

import numpy as np
import pytest

from hal.zenoh_session import free_loopback_port
from rt_controller.logtools.reader import read_log
from tests.support import free_endpoint, run_hil, start_hil_up, wait_until
from tests.support.foxglove_ws import FoxgloveClient

pytestmark = [pytest.mark.integration, pytest.mark.slow]

RUN = ("--lockstep", "--law", "ioc", "--duration", "60", "--json")
AT = 2500
"""Late in the 3000-tick run, so the set arrives before it with seconds to spare."""
COLUMNS = ("tick", "q", "dq", "f", "u", "tau", "cost", "param_set")


def _finish(proc) -> dict:
    try:
        out, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:  # pragma: no cover - only on a hang
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 0, err[-3000:]
    return json.loads(out.strip().splitlines()[-1])


def _key() -> tuple[str, str]:
    return ("--key-file", os.environ["HIL_KEY_FILE"])


def _cycles(path) -> dict[str, np.ndarray]:
    log = read_log(path)
    return {c: np.asarray(log.cycles[c]) for c in COLUMNS}


def _same(a: dict, b: dict) -> bool:
    return all(np.array_equal(a[c], b[c], equal_nan=True) for c in COLUMNS)


def _foxglove_run(tmp_path, name: str, *flags: str) -> tuple[dict, dict]:
    """One monitored run; the kp set from Foxglove at :data:`AT`; (summary, the set's reply)."""
    port = free_loopback_port()
    proc = start_hil_up(
        free_endpoint(), tmp_path / f"{name}.mcap", *RUN, *_key(),
        "--monitor", "--monitor-port", str(port), *flags,
    )  # fmt: skip
    client = None
    try:
        client = FoxgloveClient.open(f"ws://127.0.0.1:{port}", attempts=1200)
        # the monitor answers with what the controller says: nothing until it is up (a cold
        # numba cache takes its time)
        assert wait_until(
            lambda: client.get_parameters(["gains.kp"]) == {"gains.kp": 0.13},
            timeout_s=240,
            poll_s=0.5,
        )
        reply = client.set_parameters({"gains.kp": 0.3, "hil.at_tick": AT}, timeout=240)
    except BaseException:
        os.killpg(proc.pid, signal.SIGKILL)
        raise
    finally:
        if client is not None:
            client.ws.close_socket()
    return _finish(proc), reply


def test_a_foxglove_set_lands_at_its_tick_and_equals_hil_param(tmp_path):
    base = _finish(start_hil_up(free_endpoint(), tmp_path / "base.mcap", *RUN, *_key()))
    tuned, reply = _foxglove_run(tmp_path, "fox", "--allow-tuning")
    assert reply["gains.kp"] == 0.3
    assert f"accepted at tick {AT}" in reply["hil.last_outcome"]
    log = read_log(tmp_path / "fox.mcap")
    (rec,) = log.parameters
    assert rec["accepted"] and rec["tick"] == AT and rec["at_tick"] == AT
    assert rec["changes"] == [{"key": "gains.kp", "old": 0.13, "new": 0.3}]
    assert rec["source"].startswith("hil monitor")
    assert tuned["J"] != base["J"]
    replay = run_hil(["replay", str(tmp_path / "fox.mcap"), "--tol", "1e-9"], timeout_s=300)
    assert replay.returncode == 0, replay.stdout + replay.stderr

    ep = free_endpoint()
    proc = start_hil_up(ep, tmp_path / "param.mcap", *RUN, *_key())
    try:
        get = ["param", "get", "--zenoh-endpoint", ep, "--timeout", "1", *_key()]
        assert wait_until(lambda: run_hil(get, 60).returncode == 0, timeout_s=120, poll_s=0.2)
        sent = run_hil(
            ["param", "set", "gains.kp=0.3", "--at-tick", str(AT), "--zenoh-endpoint", ep,
             *_key(), "--timeout", "240"],
            timeout_s=300,
        )  # fmt: skip
    except BaseException:
        os.killpg(proc.pid, signal.SIGKILL)
        raise
    by_param = _finish(proc)
    assert sent.returncode == 0, sent.stderr
    assert by_param["J"] == tuned["J"]
    assert _same(_cycles(tmp_path / "fox.mcap"), _cycles(tmp_path / "param.mcap"))


def test_without_allow_tuning_a_foxglove_set_is_refused_and_changes_nothing(tmp_path):
    base = _finish(start_hil_up(free_endpoint(), tmp_path / "base.mcap", *RUN, *_key()))
    summary, reply = _foxglove_run(tmp_path, "ro")
    assert reply["gains.kp"] == 0.13 and "--allow-tuning" in reply["hil.last_outcome"]
    assert read_log(tmp_path / "ro.mcap").parameters == []
    assert summary["J"] == base["J"]
    assert _same(_cycles(tmp_path / "base.mcap"), _cycles(tmp_path / "ro.mcap"))
