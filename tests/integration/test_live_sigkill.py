"""The live service's MCAP log after a SIGKILLed controller (realtime ``hil up`` rig, natively
over CAN on ``udp_multicast`` and zenoh on loopback, each run on ports of its own): the log
still yields every cycle that had reached the disk before the kill, read with the ``mcap``
library's stream reader (how much a kill loses, at most the 0.5 s flush interval, is a timing
figure: reported, not asserted); the DSP took the dead controller's torque off.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.exceptions import McapError
from mcap.records import Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from hal.joint_client import JointClient
from rt_controller.logtools.reader import read_log
from rt_controller.rig.processes import Rig
from rt_controller.runtime.recorder import CONFIG_METADATA, CYCLE_TOPIC, RUN_METADATA
from tests.support import wait_until
from tests.support.joint import next_status, read_until
from tests.support.live_rig import CFG, PERIOD_S, RATE_HZ, rig_options, wait_for_cycles
from tests.support.proc import alive, children_of

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]


def stream_cycles(path: Path) -> tuple[list[dict[str, Any]], bool, dict[str, dict[str, str]]]:
    """Read a possibly unfinished MCAP file with mcap's stream reader: the cycles of every
    complete chunk, whether a footer was found, and the metadata."""
    topics: dict[int, str] = {}
    cycles: list[dict[str, Any]] = []
    metadata: dict[str, dict[str, str]] = {}
    footer = False
    schemas = 0
    size = path.stat().st_size
    with path.open("rb") as fh:
        reader = StreamReader(fh, validate_crcs=True, record_size_limit=size)
        records = reader.records
        while True:
            try:
                rec = next(records)
            except StopIteration:
                break
            except (McapError, EOFError, ValueError) as exc:
                # Only the unfinished record at the very end of the file may fail to read (the
                # reader got to the end of the file trying); anywhere else it is corruption.
                assert fh.tell() == size, f"unreadable at byte {fh.tell()} of {size}: {exc!r}"
                break
            if isinstance(rec, Schema):
                schemas += 1
            elif isinstance(rec, Channel):
                topics[rec.id] = rec.topic
            elif isinstance(rec, Message) and topics.get(rec.channel_id) == CYCLE_TOPIC:
                cycles.append(json.loads(rec.data))  # a complete chunk: must be valid JSON
            elif isinstance(rec, Metadata):
                metadata[rec.name] = dict(rec.metadata)
            elif isinstance(rec, Footer):
                footer = True
    assert schemas >= 1
    return cycles, footer, metadata


def test_sigkilled_controller_log_keeps_every_flushed_cycle(tmp_path):
    """Without a clock: wait (generously) until the running controller's log on disk holds 4 s
    of cycles, i.e. it flushed by itself; SIGKILL it; the file still yields every one of them
    and nothing after a hole. The recorder's own process outlives the controller and finishes
    the file (footer and summary). How many ticks the kill lost is reported, not asserted."""
    log = tmp_path / "killed.mcap"
    # the rig uses the test session's key, so that the observer can verify the DSP's frames
    key = Path(os.environ["HIL_KEY_FILE"])
    opts = rig_options(
        log,
        law="ioc",
        duration_s=600.0,
        extra_emulator=["--json"],
        key_file=key,
    )
    with Rig(opts) as rig, JointClient.open(opts.can, CFG) as observer:  # listens only
        rig.start()
        on_disk = wait_for_cycles(log, round(4.0 * RATE_HZ), rig)
        ctl = next(c for c in rig.children if c.name == "controller")
        assert ctl.proc.poll() is None, ctl.tail()
        before = next_status(observer, 60.0)
        writers = children_of(ctl.proc.pid)
        assert len(writers) == 1, writers
        kill_ns = time.monotonic_ns()
        os.kill(ctl.proc.pid, signal.SIGKILL)
        assert ctl.proc.wait(30) == -signal.SIGKILL
        for pid in writers:  # the orphaned recorder finishes the file, then exits
            assert wait_until(lambda pid=pid: not alive(pid), 60.0), "recorder still running"
        # Stop the emulator only once the torque is off: a busy host may run it behind real
        # time, and a SIGTERM before it reached the watchdog's physics step would end it untripped.

        def torque_off() -> bool:
            return observer.status is not None and not observer.status.torque_enabled

        assert read_until(observer, torque_off, 60.0), (
            "the DSP kept the torque on after the controller was killed"
        )
        codes = rig.stop()
        emu = next(c for c in rig.children if c.name == "emulator")
        emulator = json.loads(next(ln for ln in emu.output().splitlines() if ln.startswith("{")))
    assert codes == {"controller": -signal.SIGKILL, "vision": 0, "emulator": 0}

    cycles, footer, metadata = stream_cycles(log)
    assert footer, "the recorder's own process finishes the file"
    assert {CONFIG_METADATA, RUN_METADATA} <= set(metadata)
    ticks = np.array([c["tick"] for c in cycles])
    missed = np.array([c["missed_periods"] for c in cycles])
    # every tick up to the last record is there (realtime ticks may skip missed periods)
    assert np.array_equal(np.diff(ticks), 1 + missed[1:])
    # everything that was on disk before the kill is still there, record for record
    seen = on_disk["tick"]
    assert len(cycles) >= len(seen) and np.array_equal(ticks[: len(seen)], seen)
    assert [c["t_ns"] for c in cycles[: len(seen)]] == list(on_disk["t_ns"])
    lost_s = (kill_ns - cycles[-1]["t_ns"]) / 1e9
    print(f"SIGKILL: {len(cycles)} cycles kept; the last one {lost_s:.2f} s before the kill")

    # logread reads the same file and says it is truncated
    loaded = read_log(log)
    assert loaded.n_cycles == len(cycles)
    assert not loaded.truncated and loaded.notes == [], loaded.notes
    # the dead controller's torque was removed by the DSP (its watchdog, 3 periods on the DSP
    # clock, if the torque was on at the kill; a busy host may have had the DSP's protection
    # take it off before, which the run's emulator summary then names)
    assert emulator["drive_state"] != "operation_enabled"
    if before.torque_enabled:
        assert emulator["drive_state"] == "fault" and emulator["faults"], emulator
    if emulator["watchdog_trips"]:
        lat = emulator["last_trip_latency_ms"]
        assert 3 * PERIOD_S * 1e3 - 1e-6 <= lat <= 3 * PERIOD_S * 1e3 + 1.0, lat
    print(f"DSP at the end: {emulator['drive_state']}, faults {emulator['faults']}")
