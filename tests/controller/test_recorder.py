"""MCAP recording: read-back with the mcap library, each record written before its call returns,
flushes that a SIGKILL cannot undo, and counted (never raised) bad records and write failures."""

from __future__ import annotations

import base64
import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import time

import can
import numpy as np
import pytest
from mcap.reader import make_reader

from hal.config import config_from_json
from rt_controller.errors import LogError
from rt_controller.logtools.reader import read_log
from rt_controller.runtime.recorder import (
    CAN_RX_TOPIC,
    CAN_TX_TOPIC,
    CYCLE_TOPIC,
    DIAGNOSTICS_TOPIC,
    EVENTS_TOPIC,
    PARAMETERS_TOPIC,
    VISION_TOPIC,
    CycleRecorder,
    cycle_schema,
)
from tests.support import wait_until


def cycle(i: int, t0: int = 1_000_000_000, period_ns: int = 20_000_000) -> dict:
    """A plausible cycle record (numpy arrays, as the loop produces them)."""
    return {
        "tick": i,
        "t_ns": t0 + i * period_ns,
        "sim_time_s": None,
        "lateness_us": 10.0 + i,
        "read_us": 3.0,
        "solve_us": 40.0,
        "write_us": 5.0,
        "cycle_us": 60.0,
        "deadline_miss": False,
        "missed_periods": 0,
        "q": np.array([0.5, -0.5]),
        "dq": np.array([0.0, 0.1]),
        "f": np.array([-120.0 + i, -160.0]),
        "f_age_ms": 3.2,
        "state_age_ms": 1.0,
        "f_valid": True,
        "f_stale": False,
        "xi": np.array([0.1, 0.2]),
        "u": np.array([1.0, 2.0]),
        "tau": np.array([3.0, 4.0]),
        "tau_saturated": False,
        "law": "rhc",
        "residual": 1e-6,
        "iterations": np.int64(5),
        "fallback": False,
        "cost": 2.0,
        "V": 10.0,
    }


def test_read_back_with_mcap_library(tmp_path, cfg):
    path = tmp_path / "run.mcap"
    frame = can.Message(arbitration_id=0x123, data=bytes(range(8)), is_extended_id=False)
    with CycleRecorder(path, cfg, run_info={"law": "rhc", "rate_hz": 50}) as rec:
        for i in range(100):
            c = cycle(i)
            if i == 7:
                c["residual"] = float("nan")
            assert rec.record_cycle(c)
            rec.record_can(frame, c["t_ns"] + 1, "rx")
            rec.record_can(frame, c["t_ns"] + 2, "tx")
        rec.record_vision(b"\x00\x01payload\xff", 1_500_000_000)
    assert rec.finished and rec.error is None
    assert rec.written == 100 + 200 + 1 and rec.dropped == 0

    with path.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None
        topics = {ch.topic: ch for ch in summary.channels.values()}
        assert set(topics) == {
            CYCLE_TOPIC,
            CAN_RX_TOPIC,
            CAN_TX_TOPIC,
            VISION_TOPIC,
            DIAGNOSTICS_TOPIC,
            PARAMETERS_TOPIC,
            EVENTS_TOPIC,
        }
        for ch in topics.values():
            assert ch.message_encoding == "json"
            schema = summary.schemas[ch.schema_id]
            assert schema.encoding == "jsonschema"
            assert json.loads(schema.data)["type"] == "object"
        assert summary.schemas[topics[CYCLE_TOPIC].schema_id].name == "hil.ControllerCycle"
        counts = summary.statistics.channel_message_counts
        assert counts[topics[CYCLE_TOPIC].id] == 100
        cycles = [json.loads(m.data) for _, _, m in reader.iter_messages(topics=[CYCLE_TOPIC])]
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}

    assert [c["tick"] for c in cycles] == list(range(100))
    assert cycles[3]["f"] == [-117.0, -160.0] and cycles[3]["iterations"] == 5
    assert cycles[7]["residual"] is None  # NaN is not JSON: written as null
    assert set(cycles[0]) >= set(cycle_schema()["required"])
    assert config_from_json(metadata["hil.config"]["json"]) == cfg
    run = metadata["hil.run"]
    assert run["law"] == "rhc" and run["rate_hz"] == "50" and run["clock"] == "realtime"
    for key in ("start_wall_time", "hostname", "hil_version", "mcap_version", "python_version"):
        assert run[key]
    assert metadata["hil.recorder"]["dropped"] == "0"

    log = read_log(path)
    assert not log.truncated and log.notes == []
    assert log.config == cfg and log.n_cycles == 100
    assert log.cycles["f"].shape == (100, 2) and math.isnan(log.cycles["residual"][7])
    assert log.cycles["deadline_miss"].dtype == bool
    assert log.can_rx[0]["data"] == bytes(range(8)).hex()
    assert log.can_rx[0]["arbitration_id"] == 0x123
    assert len(log.can_tx) == 100 and log.can_tx[0]["t_ns"] == 1_000_000_002
    assert base64.b64decode(log.vision[0]["data"]) == b"\x00\x01payload\xff"


def test_cycle_schema_is_foxglove_compatible():
    """Foxglove's JSON Schema parser needs one string type per field and no $ref."""
    schema = cycle_schema()
    assert schema["type"] == "object"
    for name, field in schema["properties"].items():
        assert isinstance(field["type"], str), name
        assert "$ref" not in json.dumps(field), name
        if field["type"] == "array":
            assert field["items"]["type"] == "number", name
    assert set(schema["required"]) <= set(schema["properties"])


def test_each_record_is_written_before_its_call_returns(tmp_path, cfg):
    with CycleRecorder(tmp_path / "now.mcap", cfg) as rec:
        for i in range(5):
            assert rec.record_cycle(cycle(i))
            assert rec.written == i + 1
        assert rec.record_vision(b"v", 1) and rec.written == 6
    assert rec.as_dict() == {
        CYCLE_TOPIC: 5,
        CAN_RX_TOPIC: 0,
        CAN_TX_TOPIC: 0,
        VISION_TOPIC: 1,
        DIAGNOSTICS_TOPIC: 0,
        PARAMETERS_TOPIC: 0,
        EVENTS_TOPIC: 0,
        "written": 6,
        "dropped": 0,
        "encode_errors": 0,
        "images_written": 0,
        "image_errors": 0,
        "scene_errors": 0,
        "live_errors": 0,
        "backlog_bytes": 0,
    }


def test_flush_puts_every_record_so_far_on_disk(tmp_path, cfg):
    path = tmp_path / "open.mcap"
    with CycleRecorder(path, cfg) as rec:
        for i in range(20):
            rec.record_cycle(cycle(i))
        rec.flush()
        log = read_log(path)  # what a SIGKILL now would leave
        assert log.n_cycles == 20 and log.truncated and log.config == cfg
    assert read_log(path).truncated is False


def test_records_flush_by_themselves_once_the_interval_has_passed(tmp_path, cfg):
    """No clock is faked: waiting longer than ``flush_interval_s`` makes the next record (or
    ``flush_if_due``, which the recorder process calls while it waits) flush the file."""
    path = tmp_path / "due.mcap"
    with CycleRecorder(path, cfg, flush_interval_s=0.05) as rec:
        for i in range(10):
            rec.record_cycle(cycle(i))
        time.sleep(0.06)
        rec.record_cycle(cycle(10))
        assert read_log(path).n_cycles == 11
        rec.record_cycle(cycle(11))
        time.sleep(0.06)
        rec.flush_if_due()
        assert read_log(path).n_cycles == 12


def test_a_record_that_cannot_be_encoded_is_counted_and_the_rest_written(tmp_path, cfg):
    path = tmp_path / "bad.mcap"
    with CycleRecorder(path, cfg) as rec:
        assert rec.record_cycle(cycle(0))
        bad = cycle(1)
        bad["u"] = object()
        assert rec.record_cycle(bad) is False
        assert rec.record_cycle(cycle(2))
    assert rec.as_dict()["encode_errors"] == 1 and rec.dropped == 0 and rec.written == 2
    assert list(read_log(path).cycles["tick"]) == [0, 2]


FULL_DISK = textwrap.dedent(
    """
    import resource, signal, sys
    from hal.config import load_config
    from rt_controller.errors import LogError
    from tests.controller.test_recorder import cycle
    from rt_controller.runtime.recorder import CycleRecorder

    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # past the limit, a write fails (EFBIG)
    resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))
    rec = CycleRecorder(sys.argv[1], load_config(), chunk_size=4096)
    n = 0
    while rec.record_cycle(cycle(n)):
        n += 1
    assert rec.error is not None and rec.closed and rec.dropped == 1, rec.as_dict()
    assert rec.record_cycle(cycle(n)) is False and rec.dropped == 2
    try:
        with rec:
            pass
    except LogError as exc:
        print(n, exc)
    """
)


def test_a_write_failure_ends_the_log_and_is_reported(tmp_path):
    path = tmp_path / "full.mcap"
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    proc = subprocess.run(
        [sys.executable, "-c", FULL_DISK, str(path)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=root,
        env={**os.environ, "PYTHONPATH": root},
    )
    assert proc.returncode == 0, proc.stderr
    written, message = proc.stdout.split(" ", 1)
    assert "is incomplete" in message and int(written) > 100
    log = read_log(path)  # the chunks before the failure stay readable
    assert log.truncated and 0 < log.n_cycles <= int(written)
    assert np.array_equal(log.cycles["tick"], np.arange(log.n_cycles))


def test_close_is_idempotent_and_refuses_late_records(tmp_path, cfg):
    rec = CycleRecorder(tmp_path / "c.mcap", cfg)
    rec.record_cycle(cycle(0))
    rec.close()
    rec.close()
    with rec:
        pass
    assert rec.closed and rec.finished
    assert rec.record_cycle(cycle(1)) is False
    assert rec.record_vision(b"x", 1) is False
    assert rec.dropped == 2 and rec.as_dict()[CYCLE_TOPIC] == 1


def test_bad_arguments(tmp_path, cfg):
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(LogError, match="cannot create MCAP log"):
        CycleRecorder(blocker / "x.mcap", cfg)
    with pytest.raises(LogError, match="flush_interval_s"):
        CycleRecorder(tmp_path / "y.mcap", cfg, flush_interval_s=0)
    with CycleRecorder(tmp_path / "z.mcap", cfg) as rec, pytest.raises(LogError, match="'rx'"):
        rec.record_can(can.Message(arbitration_id=1), 0, "sideways")


CHILD = textwrap.dedent(
    """
    import sys, time
    from hal.config import load_config
    from rt_controller.runtime.recorder import CycleRecorder

    rec = CycleRecorder(sys.argv[1], load_config(), run_info={"law": "ioc"})
    period = 5_000_000  # 200 Hz
    nxt = time.monotonic_ns()
    i = 0
    while True:
        now = time.monotonic_ns()
        rec.record_cycle({"tick": i, "t_ns": now, "lateness_us": (now - nxt) / 1e3,
                          "deadline_miss": False, "missed_periods": 0, "f": [1.0, 2.0]})
        if i == 0:
            print("ready", flush=True)
        i += 1
        nxt += period
        time.sleep(max(0.0, (nxt - time.monotonic_ns()) / 1e9))
    """
)


def flushed_ticks(path) -> int:
    """Cycles readable from the file of a still running writer (0 if nothing flushed yet)."""
    if not path.exists() or path.stat().st_size == 0:
        return 0
    try:
        return read_log(path).n_cycles
    except Exception:  # a header still being written: nothing readable yet
        return 0


@pytest.mark.slow
def test_sigkilled_writer_keeps_every_flushed_chunk(tmp_path):
    """Durability without a clock: while the writer runs, wait (generously) until its file on
    disk holds at least 200 cycles, i.e. records flushed it by themselves; SIGKILL it;
    everything seen before the kill is still there, from tick 0 without a hole. (How much a
    kill loses, about ``flush_interval_s``, is a timing figure: not asserted.)"""
    path = tmp_path / "killed.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(path)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout.readline().strip() == "ready"
        assert wait_until(lambda: flushed_ticks(path) >= 200, timeout_s=120.0, poll_s=0.1), (
            "the writer never flushed 200 cycles to disk while running"
        )
        seen = flushed_ticks(path)
        assert proc.poll() is None, "the writer must still be running when it is killed"
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(timeout=10)
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL

    log = read_log(path)
    assert log.truncated and log.notes
    assert log.run_info["law"] == "ioc" and log.config is not None
    ticks = log.cycles["tick"]
    assert np.array_equal(ticks, np.arange(len(ticks)))  # every finished chunk, no holes
    assert len(ticks) >= seen >= 200  # nothing that was on disk before the kill is lost
