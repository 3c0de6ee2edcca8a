"""Findings of the walk of the live tools: ``hil monitor`` says on stderr that it waits for the
zenoh hub (after a second, when its wait is long enough for that to matter) and when the rig it
watches stops sending records; its exit codes stay as they were. The rig is played by a zenoh
hub in this process that publishes a few cycle records and then falls silent. No wall-clock
assertion: only what the monitor says is asserted."""

from __future__ import annotations

import json
import socket
import subprocess
import time

import pytest

from tests.support import REPO, hil_command
from tests.support.proc import WAIT_S, reaped

pytestmark = pytest.mark.integration


def _key(tmp_path) -> str:
    key = tmp_path / "rig.key"
    subprocess.run([*hil_command(), "keygen", str(key)], check=True, capture_output=True)
    return str(key)


def test_a_monitor_waiting_for_the_hub_says_so_and_still_fails_with_exit_2(tmp_path):
    key = _key(tmp_path)
    with socket.socket() as lsn:  # a port nobody else takes meanwhile; it speaks no zenoh
        lsn.bind(("127.0.0.1", 0))
        lsn.listen(8)
        endpoint = f"tcp/127.0.0.1:{lsn.getsockname()[1]}"
        cmd = [*hil_command(), "monitor", "--port", "0", "--duration", "3"]
        cmd += ["--key-file", key, "--zenoh-endpoint", endpoint]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=WAIT_S, cwd=REPO)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert lines[0].startswith(f"hil monitor: waiting for the zenoh hub at {endpoint}"), lines
    assert lines[-1].startswith(f"hil monitor: error: zenoh: no hub at {endpoint}"), lines
    assert len(lines) == 2 and "Traceback" not in done.stderr


def test_a_monitor_says_when_the_rig_it_watches_stops_sending(tmp_path):
    from hal.zenoh_session import KEY_CONTROLLER_CYCLE, free_loopback_port, open_session

    key = _key(tmp_path)
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    hub = open_session(listen=True, endpoint=endpoint)
    try:
        pub = hub.publisher(KEY_CONTROLLER_CYCLE)
        cmd = [*hil_command(), "monitor", "--port", "0", "--duration", "9", "--json"]
        cmd += ["--key-file", key, "--zenoh-endpoint", endpoint]
        proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            start_new_session=True, cwd=REPO,
        )  # fmt: skip
        with reaped(proc):
            seen = []
            for line in proc.stderr:  # the monitor serves: its subscriptions are declared
                seen.append(line)
                if "Foxglove WebSocket on" in line:
                    break
            for tick in range(1, 21):  # the rig runs a while, then stops
                pub.put(json.dumps({"tick": tick, "param_set": 0}).encode())
                time.sleep(0.05)
            out, err = proc.communicate(timeout=WAIT_S)
    finally:
        hub.close()
    err = "".join(seen) + err
    assert proc.returncode == 0, err
    assert json.loads(out)["cycles"] > 0, out  # it did see the rig
    stopped = [ln for ln in err.splitlines() if "the rig went silent" in ln]
    assert len(stopped) == 1 and "no record for" in stopped[0], err
