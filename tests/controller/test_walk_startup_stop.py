"""A standalone ``hil controller`` stopped during its start-up, with no hub on its zenoh
endpoint: the stop ends the recorder's wait for the live stream's hub, not that wait's own
timeout, and the log is still finished."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess

from hal.bus import isolated_spec
from tests.support import REPO, free_endpoint, hil_command
from tests.support.proc import WAIT_S


def test_a_stop_during_start_up_ends_the_live_streams_wait(tmp_path):
    endpoint = free_endpoint()  # nobody listens there: the recorder waits for a hub
    log = tmp_path / "run.mcap"
    args = ["controller", "--can", isolated_spec("udp_multicast"), "--zenoh-endpoint", endpoint]
    proc = subprocess.Popen(
        [*hil_command(), *args, "--no-rt", "--json", "--log", str(log)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
        cwd=REPO,
    )
    try:
        first = b""
        while b"logging to" not in first:  # its signal handlers are in place
            assert select.select([proc.stderr], [], [], WAIT_S)[0], "no start-up line"
            line = proc.stderr.readline()
            assert line, f"the controller exited early: {first!r}"
            first += line
        os.kill(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=WAIT_S)
    finally:
        if proc.poll() is None:  # pragma: no cover - only on a hang
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    err = err.decode()
    summary = json.loads(out)
    assert proc.returncode == 0, err
    assert (summary["end_reason"], summary["stop_signal"]) == ("stopped", "SIGINT"), summary
    assert summary["recorder"]["written"] >= 1 and not summary["recorder"].get("error"), summary
    assert "after 5 s" not in err, err  # the hub's wait ran to its own timeout
    assert "stopped while waiting for the hub" in err, err
