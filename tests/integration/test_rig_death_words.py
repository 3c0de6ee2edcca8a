"""``hil up``'s summary after a process of the rig ended says what this run did, and how the
process ended, also when the answer is not a kill:

* a rig process stopped in order by a SIGTERM from elsewhere exits 0, which is not "exited with
  status 0" as if nothing happened: the summary says a signal the rig did not send stopped it;
* ``--log FILE --force`` over an earlier run's log: a process that dies (or refuses to start)
  before the controller replaced the file must not make the earlier run's ticks, J and
  finished log this run's summary (nor turn bad usage, exit 2, into a run not clean).

The real ``hil up`` runs, as a user starts it; the waits poll, no wall-clock assertion.
"""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import pytest

from hal.bus import isolated_spec
from hal.zenoh_session import free_loopback_port
from tests.support import cycles_logged, run_hil, start_hil_up
from tests.support.proc import WAIT_S, child_running, processes_mentioning, reaped, wait_for

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

TICKS_FIRST = 30


def _endpoint() -> str:
    return f"tcp/127.0.0.1:{free_loopback_port()}"


def _summary(out: str, err: str, rc: int) -> dict:
    lines = [line for line in out.splitlines() if line.startswith("{")]
    assert len(lines) == 1, f"no JSON summary (exit {rc}):\n{out}\n{err}"
    assert "Traceback" not in err, err
    return json.loads(lines[0])


def _earlier_log(tmp_path: Path) -> tuple[Path, bytes]:
    """A finished log of an earlier, short lockstep run, and its bytes."""
    log = tmp_path / "run.mcap"
    private = ["--can", isolated_spec("udp_multicast"), "--zenoh-endpoint", _endpoint()]
    done = run_hil(
        ["up", "--lockstep", "--duration", "0.5", "--json", "--log", str(log), *private], 180
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return log, log.read_bytes()


def test_a_rig_process_stopped_by_a_signal_from_elsewhere_is_said_so(tmp_path):
    ep, log = _endpoint(), tmp_path / "run.mcap"
    with reaped(start_hil_up(ep, log, "--duration", "600", "--json")) as proc:
        wait_for(lambda: cycles_logged(log) >= TICKS_FIRST, "the first ticks", proc)
        pid = child_running(proc.pid, "vision")
        assert pid is not None, "no vision child"
        os.kill(pid, signal.SIGTERM)
        out, err = proc.communicate(timeout=WAIT_S)
    summary = _summary(out, err, proc.returncode)
    assert proc.returncode == 1, err
    said = "vision stopped by a signal the rig did not send (exit status 0) at tick "
    assert summary["end_reason"].startswith(said), summary["end_reason"]
    assert summary["ended_by"]["process"] == "vision" and summary["ended_by"]["exit_code"] == 0
    assert said in err.strip().splitlines()[-1], err
    assert not processes_mentioning(ep)


def test_bad_usage_over_an_earlier_runs_log_is_still_bad_usage(tmp_path):
    """A CAN interface that is not there: the emulator exits 2 before any tick. The earlier
    run's log at ``--log`` (given with --force) is not taken for this run's: one line, exit 2."""
    log, _ = _earlier_log(tmp_path)
    args = ["up", "--lockstep", "--duration", "2", "--json", "--force", "--log", str(log)]
    done = run_hil([*args, "--can", "socketcan:hilnone0", "--zenoh-endpoint", _endpoint()], 120)
    assert done.returncode == 2, (done.stdout, done.stderr[-2000:])
    # after the warning a bus that may hold hardware gets (an emulated DSP starts on it)
    warning, _, err = done.stderr.partition("\n")
    assert warning.startswith("hil up: warning: socketcan:hilnone0 may be"), done.stderr
    assert err.startswith("hil up: error:"), done.stderr
    assert "exited with status 2" in done.stderr and "Traceback" not in done.stderr
    assert not done.stdout.strip()
    # (with --force the controller may have replaced the earlier log before the rig stopped it:
    # its recorder opens before its links; either way nothing of the earlier run is reported)


def test_a_death_before_the_log_is_replaced_does_not_report_the_earlier_run(tmp_path):
    """The emulator killed as it starts: the controller is stopped before it opens its log, so
    the file at ``--log`` is still the earlier run's; the summary must not give its ticks."""
    log, before = _earlier_log(tmp_path)
    ep = _endpoint()
    with reaped(
        start_hil_up(ep, log, "--lockstep", "--duration", "2", "--json", "--force")
    ) as proc:
        wait_for(lambda: child_running(proc.pid, "emulator") is not None, "the emulator", proc)
        os.kill(child_running(proc.pid, "emulator"), signal.SIGKILL)
        out, err = proc.communicate(timeout=WAIT_S)
    summary = _summary(out, err, proc.returncode)
    assert proc.returncode == 1, err
    assert summary["ended_by"]["process"] == "emulator", summary
    assert summary["ticks"] in (None, 0), summary  # the earlier run had 25
    assert summary["end_reason"].endswith("before its first tick"), summary["end_reason"]
    if log.read_bytes() == before:  # the controller never opened it (the usual case)
        assert summary["log"] is None and "no log of this run" in str(summary["problems"])
    assert not processes_mentioning(ep)
