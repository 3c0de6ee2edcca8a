"""The MCAP recorder in a process of its own: the same log as a ``CycleRecorder`` in this
process, flushed while it waits, counted drops that never block a realtime tick, backpressure for
lockstep, and the failures of either process."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import can
import pytest
from mcap.reader import make_reader

from rt_controller.errors import LogError
from rt_controller.logtools.reader import read_log
from rt_controller.runtime.counters import run_problems
from rt_controller.runtime.recorder import CycleRecorder
from rt_controller.runtime.recorder_process import RecorderProcess
from tests.controller.test_recorder import cycle, flushed_ticks
from tests.support import wait_until
from tests.support.proc import alive

FRAME = can.Message(arbitration_id=0x123, data=bytes(range(8)), is_extended_id=False)


def _feed(rec, n: int, start: int = 0) -> None:
    """What a tick records: a received and a sent frame, a vision payload, the cycle."""
    for i in range(start, start + n):
        c = cycle(i)
        rec.record_can(FRAME, c["t_ns"] + 1, "rx")
        rec.record_can(FRAME, c["t_ns"] + 2, "tx")
        rec.record_vision(b"\x00payload" + bytes([i % 256]), c["t_ns"] + 3)
        rec.record_cycle(c)
    rec.record_diagnostics({"t_ns": 7, "tick": n, "status": []}, final=True)


def _contents(path: Path) -> str:
    """Everything read back, as JSON text (NaN compares equal there)."""
    log = read_log(path)
    assert not log.truncated and log.notes == []
    return json.dumps(
        {
            "cycles": {k: v.tolist() for k, v in log.cycles.items()},
            "can_rx": log.can_rx,
            "can_tx": log.can_tx,
            "vision": log.vision,
            "diagnostics": log.diagnostics,
            "counts": log.topic_counts,
        },
        sort_keys=True,
    )


def test_the_process_writes_the_log_a_recorder_here_writes(tmp_path, cfg):
    with CycleRecorder(tmp_path / "here.mcap", cfg) as rec:
        _feed(rec, 300)
    with RecorderProcess(tmp_path / "process.mcap", cfg, run_info={"law": "rhc"}) as remote:
        _feed(remote, 300)
    assert remote.finished and remote.error is None
    assert remote.as_dict() == rec.as_dict()  # every topic, written, dropped
    assert _contents(tmp_path / "process.mcap") == _contents(tmp_path / "here.mcap")
    info = read_log(tmp_path / "process.mcap").run_info
    assert info["law"] == "rhc" and info["pid"] == str(os.getpid())  # the controller's, not its


def test_a_quiet_log_reaches_the_disk_and_survives_a_killed_recorder(tmp_path, cfg):
    """The child flushes a log that is due while it waits for more (no record arrives after
    the first 20); SIGKILLed then, it leaves those 20 readable."""
    path = tmp_path / "quiet.mcap"
    rec = RecorderProcess(path, cfg, flush_interval_s=0.05)
    _feed(rec, 20)
    assert wait_until(lambda: flushed_ticks(path) == 20, timeout_s=60.0, poll_s=0.05)
    os.kill(rec.pid, signal.SIGKILL)
    rec.close(timeout=5)
    assert "recorder process" in rec.error
    log = read_log(path)
    assert log.truncated and list(log.cycles["tick"]) == list(range(20))


def test_each_log_has_a_process_that_ends_with_it(tmp_path, cfg):
    for k in range(3):
        with RecorderProcess(tmp_path / f"run{k}.mcap", cfg) as rec:
            _feed(rec, 10 * (k + 1))
        assert rec.as_dict()["/controller/cycle"] == 10 * (k + 1)
        assert not alive(rec.pid)
    assert [read_log(tmp_path / f"run{k}.mcap").n_cycles for k in range(3)] == [10, 20, 30]


def test_a_bad_log_path_is_a_clear_error(tmp_path, cfg):
    (tmp_path / "file").write_text("not a folder")
    with pytest.raises(LogError, match="cannot create MCAP log"):
        RecorderProcess(tmp_path / "file" / "run.mcap", cfg)
    with RecorderProcess(tmp_path / "ok.mcap", cfg) as rec:
        _feed(rec, 5)
    assert read_log(tmp_path / "ok.mcap").n_cycles == 5


def test_a_log_made_after_the_command_line_checked_its_path_is_kept(tmp_path, cfg):
    """``hil up --log X`` without ``--force`` checks X, then starts the rig: a file X made in
    between (another run) is not replaced by this run's log."""
    other = tmp_path / "run.mcap"
    other.write_bytes(b"another run's log")
    with pytest.raises(LogError, match="exists \\(pass --force"):
        RecorderProcess(other, cfg, replace=False)
    assert other.read_bytes() == b"another run's log"
    with RecorderProcess(other, cfg) as rec:  # --force
        _feed(rec, 3)
    assert read_log(other).n_cycles == 3


def test_a_stalled_recorder_costs_a_realtime_tick_counted_drops_never_a_wait(tmp_path, cfg):
    with RecorderProcess(tmp_path / "run.mcap", cfg, backpressure=False) as rec:
        rec.outbox_limit = 4096
        os.kill(rec.pid, signal.SIGSTOP)  # the recorder gets no CPU
        try:
            kept = sum(rec.record_cycle(cycle(i)) for i in range(20_000))
        finally:
            os.kill(rec.pid, signal.SIGCONT)
        dropped = 20_000 - kept
        assert dropped > 0  # the pipe and the outbox filled up: later ticks were dropped
    counts = rec.as_dict()
    assert counts["dropped"] == dropped
    assert counts["/controller/cycle"] == kept == read_log(tmp_path / "run.mcap").n_cycles
    assert run_problems({"recorder": counts}) == [f"{dropped} log record(s) lost"]


def test_a_stalled_recorder_makes_a_lockstep_tick_wait_and_loses_nothing(tmp_path, cfg):
    with RecorderProcess(tmp_path / "run.mcap", cfg, backpressure=True) as rec:
        rec.outbox_limit = 4096
        os.kill(rec.pid, signal.SIGSTOP)
        resume = threading.Timer(0.3, os.kill, (rec.pid, signal.SIGCONT))
        resume.start()
        try:
            assert all(rec.record_cycle(cycle(i)) for i in range(20_000))
        finally:
            resume.join()
    assert rec.as_dict()["dropped"] == 0 and rec.as_dict()["/controller/cycle"] == 20_000
    assert read_log(tmp_path / "run.mcap").n_cycles == 20_000


def test_a_killed_recorder_is_reported_and_never_stops_the_loop(tmp_path, cfg):
    rec = RecorderProcess(tmp_path / "run.mcap", cfg)
    _feed(rec, 50)
    os.kill(rec.pid, signal.SIGKILL)
    # the loop goes on; a record is refused once the pipe reports the loss (the kernel
    # closes a killed process's pipes when its last thread has exited)
    i = 50
    while rec.record_cycle(cycle(i)) and i < 100_000:
        i += 1
        time.sleep(0.001)
    sent = [rec.record_cycle(cycle(j)) for j in range(i, i + 10)]
    rec.close(timeout=5)
    assert not any(sent)  # nothing is queued in vain after that
    assert rec.dropped == 11  # the refused records are counted
    assert "recorder process was killed by SIGKILL" in rec.error and not rec.finished
    with pytest.raises(LogError, match="incomplete"), rec:
        pass
    summary = {"recorder": rec.as_dict(), "log_error": rec.error}
    assert any("MCAP log is incomplete" in p for p in run_problems(summary))
    # what reached the file is the log's to say: the counts are of records sent to the child
    assert "written" not in summary["recorder"] and summary["recorder"]["sent"] >= 50


def test_the_recorder_ignores_ctrl_c_and_the_controller_ends_the_log(tmp_path, cfg):
    with RecorderProcess(tmp_path / "run.mcap", cfg) as rec:
        _feed(rec, 10)
        time.sleep(0.2)  # let the child install its handlers (no assertion on timing)
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            os.kill(rec.pid, sig)
        _feed(rec, 10, start=10)
    assert rec.error is None and read_log(tmp_path / "run.mcap").n_cycles == 20


_KILLED_CONTROLLER = textwrap.dedent(
    """
    import os, signal, sys
    from hal.config import RigConfig
    from rt_controller.runtime.recorder_process import RecorderProcess
    from tests.controller.test_recorder import cycle

    cfg = RigConfig()
    rec = RecorderProcess(sys.argv[1], cfg)
    for i in range(200):
        rec.record_cycle(cycle(i))
    print(rec.pid, flush=True)
    os.kill(os.getpid(), signal.SIGKILL)
    """
)


def test_the_recorder_finishes_the_log_of_a_sigkilled_controller(tmp_path):
    path = tmp_path / "run.mcap"
    root = Path(__file__).resolve().parents[2]
    proc = subprocess.run(
        [sys.executable, "-c", _KILLED_CONTROLLER, str(path)],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(root), "OPENBLAS_NUM_THREADS": "1"},  # as the CLI
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    pid = proc.stdout.strip()
    deadline = time.monotonic() + 60
    while alive(int(pid)) and time.monotonic() < deadline:
        time.sleep(0.02)
    assert not alive(int(pid))
    log = read_log(path)
    assert not log.truncated and log.n_cycles == 200  # a footer: the file was finished
    assert json.loads(log.recorder_info.get("written", "0")) == 200


_FULL_AT_START = textwrap.dedent(
    """
    import resource, signal, sys
    from hal.config import RigConfig
    from rt_controller.runtime.counters import run_problems
    from rt_controller.runtime.recorder_process import RecorderProcess
    from tests.controller.test_recorder import cycle

    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # inherited: past the limit a write fails
    resource.setrlimit(resource.RLIMIT_FSIZE, (64, 64))  # the log's first records do not fit
    rec = RecorderProcess(sys.argv[1], RigConfig())
    for i in range(20):
        rec.record_cycle(cycle(i))
    rec.close()
    print(rec.finished, run_problems({"recorder": rec.as_dict(), "log_error": rec.error}))
    """
)


def test_a_log_the_recorder_cannot_start_is_reported_never_raised(tmp_path):
    """The controller could create the file, the recorder process cannot write it (a full
    disk): the close reports the log incomplete and why."""
    root = Path(__file__).resolve().parents[2]
    proc = subprocess.run(
        [sys.executable, "-c", _FULL_AT_START, str(tmp_path / "run.mcap")],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(root), "OPENBLAS_NUM_THREADS": "1"},
    )
    assert proc.returncode == 0, proc.stderr
    last = proc.stdout.strip().splitlines()[-1]
    assert last.startswith("False") and "the MCAP log is incomplete: cannot create" in last, last


def test_a_record_that_cannot_be_encoded_is_counted_and_the_rest_kept(tmp_path, cfg):
    with RecorderProcess(tmp_path / "run.mcap", cfg) as rec:
        rec.record_vision(b"ok", 1)
        bad = cycle(0)
        bad["u"] = lambda: None  # not JSON
        assert rec.record_cycle(bad) is False  # counted, never raised into the tick
        _feed(rec, 5, start=1)
    counts = rec.as_dict()
    assert counts["encode_errors"] == 1 and counts["/vision/features"] == 6
    assert counts["/controller/cycle"] == 5 and rec.error is None
    assert run_problems({"recorder": counts}) == ["1 log record(s) could not be encoded"]


def _messages(path: Path) -> list[tuple[str, bytes]]:
    """Every message of the log in file order: its topic and bytes."""
    with open(path, "rb") as f:
        return [(c.topic, m.data) for _, c, m in make_reader(f).iter_messages(log_time_order=False)]


def test_lockstep_logs_of_the_same_records_hold_the_same_bytes(tmp_path, cfg):
    """Deterministic in lockstep: a recorder stalled for a while changes no byte of any message
    (the time stamps of the log shift with the start, the messages' own do not)."""
    with CycleRecorder(tmp_path / "here.mcap", cfg) as here:
        _feed(here, 200)
    paths = [tmp_path / "a.mcap", tmp_path / "b.mcap"]
    for k, path in enumerate(paths):
        with RecorderProcess(path, cfg, backpressure=True) as rec:
            if k:
                os.kill(rec.pid, signal.SIGSTOP)
                threading.Timer(0.3, os.kill, (rec.pid, signal.SIGCONT)).start()
            _feed(rec, 200)
        assert rec.dropped == 0 and rec.error is None
    a, b = (_messages(p) for p in paths)
    assert len(a) == 801 and a == b == _messages(tmp_path / "here.mcap")


@pytest.mark.parametrize("backpressure", [True, False])
def test_a_lockstep_log_is_written_at_a_lower_priority_a_realtime_one_at_ours(
    tmp_path, cfg, backpressure
):
    """Lockstep: the recorder leaves the cores to the Sync-paced chain (nice +10; the tick
    waits for it when the pipe is full); realtime: our priority, a starved recorder would drop
    records."""
    ours = os.getpriority(os.PRIO_PROCESS, 0)
    with RecorderProcess(tmp_path / "run.mcap", cfg, backpressure=backpressure) as rec:
        nice = os.getpriority(os.PRIO_PROCESS, rec.pid)
        _feed(rec, 5)
    assert nice == (min(ours + 10, 19) if backpressure else ours)
    assert read_log(tmp_path / "run.mcap").n_cycles == 5
