"""The live service end to end, natively: ``hil up`` (emulator, vision, controller as separate
processes) over CAN on ``udp_multicast`` and zenoh on loopback, and its MCAP log.

Every run gets its own CAN port (:func:`hal.bus.isolated_spec`) and zenoh port, so parallel runs
and other rigs on the host never meet. Lockstep runs are deterministic and faster than real time;
realtime runs are used where the claim is about wall-clock behaviour (SIGKILL, vision dropout).
No timing is asserted (that is ``hil bench``'s job).

What is checked (issue 5, "Tests"):

* the paper scenario in lockstep with each law: |f| below 1 px just before the t = 3 s target
  jump and again at the end, and the HIL run tracks the transport-free simulation
  (:func:`rt_controller.control.simulate.run_closed_loop` on the emulator's physics) tick by tick;
* the MCAP log reads back with the ``mcap`` library itself: one ``/controller/cycle`` message per
  tick, JSON Schema present, ``hil.config`` / ``hil.run`` metadata, raw CAN and vision messages;
* a SIGKILLed controller's log still yields every cycle that had reached the disk before the
  kill (how much a kill loses, at most the 0.5 s flush interval, is a timing figure: reported);
* a 0.5 s vision dropout (``hil vision --dropout``): stale features put the loop in hold, no NaN
  reaches the bus, the arm stays within limits and the loop converges after the features return;
* ``hil up --json`` from the command line, and a dying rig process reported with its exit status
  and stderr tail, nothing left running.

A note on the passivity-based law: with the paper's gains (eq. 34) PBC has half the gain of the
inverse-optimal law, and even the transport-free simulation only gets to |f| = 2.2 px at
t = 2.98 s and 4.8 px at 6 s (``hil simulate --law pbc --duration 2.98``): "< 1 px before the
disturbance" is out of its reach on physical grounds. PBC therefore runs 8 s (|f| < 1 px at the end)
and its pre-jump |f| is checked against the simulation; the literal 1 px claim is kept as a strict
xfail so the gap stays visible.
"""

from __future__ import annotations

import base64
import json
import math
import os
import re
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cantools
import numpy as np
import pytest
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from hal.bus import isolated_spec
from hal.can_database import DBC_PATH
from hal.config import RigConfig, config_from_json, load_config
from hal.joint_client import JointClient
from hal.vision_codec import decode_features
from rt_controller.logtools.reader import read_log
from rt_controller.rig.failures import RigProcessError
from rt_controller.rig.options import RigOptions
from rt_controller.rig.processes import Rig, run_rig
from rt_controller.runtime.recorder import (
    CAN_RX_TOPIC,
    CAN_TX_TOPIC,
    CONFIG_METADATA,
    CYCLE_TOPIC,
    RUN_METADATA,
    VISION_TOPIC,
    cycle_schema,
)
from tests.support import free_endpoint, run_hil, wait_until
from tests.support.joint import next_status, read_until
from tests.support.proc import alive, children_of, processes_mentioning

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

REPO = Path(__file__).resolve().parents[2]
LAWS = ("pbc", "ioc", "rhc")
CFG = load_config()
PERIOD_S = CFG.rates.control_period_ns / 1e9
RATE_HZ = CFG.rates.control_hz
JUMP_S = 3.0
"""The paper scenario's target jump (3 s, ScenarioConfig.jump_time)."""
TAU_MAX = np.array(CFG.robot.tau_max, dtype=float)
FEATURE_TIMEOUT_S = CFG.controller.feature_timeout_s

DURATION_S = {"pbc": 8.0, "ioc": 6.0, "rhc": 6.0}
"""Lockstep run per law: the shortest that reaches |f| < 1 px at the end (PBC: see the module
docstring; the transport-free simulation gives 0.22 px at 8 s)."""
PRE_JUMP_LIMIT_PX = {"pbc": 2.6, "ioc": 1.0, "rhc": 1.0}
"""Max |f| over t in [2.9, 3.0). PBC's bound is the physics (simulation: 2.46 px at 2.9 s)."""
SIM_TRACKING_PX = 2.0
"""Largest |f_HIL - f_simulation| at any tick. The rig adds encoder quantisation, the DSP's
velocity filter and the 60 fps camera (observed: at most 1.1 px, on a 200 px start)."""
JUMP_TRANSIENT_S = 1.0
"""After the jump, the rig on images sees it a tick later than the simulation: the gap is not
compared for this long."""
DROPOUT = (1.0, 0.5)
"""Vision dropout (start, duration) in seconds of simulation time (the issue: paused 0.5 s)."""
REALTIME_DROPOUT_START_S = 4.0
"""In real time the dropout is on the emulator's clock, which starts before the controller's
first tick; a host loaded far beyond its cores can delay that tick by seconds, so the realtime
run drops out later (the run is long enough to converge again after it)."""
DROPOUT_DURATION_S = 8.0
DQ_LIMIT = 10.0
"""rad/s: the paper scenario never comes near this (observed max 4.2 rad/s on joint 2)."""


def rig_options(log: Path, **kw: Any) -> RigOptions:
    """A rig on its own CAN port and zenoh port, logging to ``log``."""
    kw.setdefault("can", isolated_spec("udp_multicast"))
    kw.setdefault("zenoh_endpoint", free_endpoint())
    # a busy host can take longer than vision's default 10 s to bring the emulator's hub up
    kw["extra_vision"] = ["--wait", "120", *kw.get("extra_vision", [])]
    return RigOptions(log=log, **kw)


DSP_PROTECTION = re.compile(
    r"^(\d+ DSP watchdog trip\(s\)|DSP fault\(s\): .*|\d+ tick\(s\) without an enabled DSP \(.*\))$"
)
"""What may make a realtime run not clean on a busy host: the controller stalled past the DSP's
watchdog (3 periods) or its late commands let the arm exceed a DSP limit; either way the DSP's
protection took the torque off (a fault), and the ticks after ran without an enabled DSP."""


ZERO_TORQUE_MODES = {"no_state", "no_status", "fault", "disarmed", "dsp_restarted"}
"""Cycle ``law`` values in which the controller commands zero torque (a late joint state, or a
DSP that is not enabled; see hal.drive_state)."""


def assert_exit_codes(s: dict[str, Any], *, realtime: bool) -> bool:
    """All processes exit 0; in real time the controller may exit 1 (not clean), but only when
    the DSP's protection fired (see ``DSP_PROTECTION``), never for a lost log record or a crash.
    Whether the run was clean (performance claims hold only for clean runs)."""
    codes = dict(s["exit_codes"])
    clean = codes.get("controller") == 0
    if realtime and codes.get("controller") == 1:
        problems = s["problems"]
        assert problems and all(DSP_PROTECTION.match(p) for p in problems), problems
        print(f"realtime run not clean on this host: {'; '.join(problems)}")
        codes["controller"] = 0
    assert codes == {"controller": 0, "vision": 0, "emulator": 0}, s["exit_codes"]
    return clean


def norm(f: np.ndarray) -> np.ndarray:
    return np.hypot(f[:, 0], f[:, 1])


def pre_jump(cycles: dict[str, np.ndarray]) -> np.ndarray:
    """|f| at the ticks just before the disturbance: sim time in [2.9, 3.0)."""
    t = cycles["sim_time_s"]
    sel = (t >= JUMP_S - 0.1 - 1e-9) & (t < JUMP_S - 1e-9)
    assert sel.sum() == 5, t
    return norm(cycles["f"][sel])


def assert_nothing_left(token: str, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while (left := processes_mentioning(token)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not left, f"left running: {left}"


def wait_for_cycles(log: Path, n: int, rig: Rig, timeout_s: float = 120.0) -> dict[str, np.ndarray]:
    """Poll the growing log until it holds ``n`` cycles (a generous timeout: a busy host delays
    start-up and the writer); the cycles read at that moment."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for c in rig.children:
            assert c.proc.poll() is None, f"{c.name} exited early:\n{c.tail()}"
        if log.exists() and log.stat().st_size > 0:
            cycles = read_log(log, raw=False).cycles
            if len(cycles.get("tick", ())) >= n:
                return cycles
        time.sleep(0.1)
    raise AssertionError(f"the controller logged fewer than {n} cycles in {timeout_s} s")


def simulate(law: str, duration_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Transport-free closed loop on the emulator's physics: (t, f) per tick."""
    from plant_emulator.world import World
    from rt_controller.control.controller import Controller
    from rt_controller.control.simulate import run_closed_loop

    cfg = CFG.with_overrides({"controller.law": law})
    trace = run_closed_loop(World(cfg), Controller(cfg), cfg, duration_s).trace
    return trace.array("t"), trace.array("f")


@dataclass
class Run:
    summary: dict[str, Any]
    log: Path
    wall_s: float


class LockstepRuns:
    """One lockstep ``run_rig`` per law, shared by the module's tests (each takes a few s)."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.runs: dict[str, Run] = {}

    def __call__(self, law: str) -> Run:
        if law not in self.runs:
            log = self.root / f"lockstep-{law}.mcap"
            opts = rig_options(log, law=law, lockstep=True, duration_s=DURATION_S[law])
            t0 = time.monotonic()
            summary = run_rig(opts)
            self.runs[law] = Run(summary, log, time.monotonic() - t0)
        return self.runs[law]


@pytest.fixture(scope="module")
def lockstep_runs(tmp_path_factory: pytest.TempPathFactory) -> LockstepRuns:
    return LockstepRuns(tmp_path_factory.mktemp("live"))


# ------------------------------------------------------------------ (a) the paper scenario


@pytest.mark.parametrize("law", LAWS)
def test_lockstep_paper_scenario_converges_before_and_after_the_jump(lockstep_runs, law):
    run = lockstep_runs(law)
    s = run.summary
    print(f"lockstep {law} {DURATION_S[law]:g} s: {run.wall_s:.1f} s wall, J = {s['J']:.3f}")
    ticks = round(DURATION_S[law] * RATE_HZ)
    assert s["law"] == law and s["log"] == str(run.log)
    assert s["exit_codes"] == {"controller": 0, "vision": 0, "emulator": 0}
    assert s["ticks"] == ticks and s["missed_periods"] == 0
    assert s["stale_features"] == 0 and s["stale_states"] == 0
    assert s["f_final_norm"] < 1.0, s["f_final"]
    assert math.isfinite(s["J"]) and s["J"] > 0

    cycles = read_log(run.log, raw=False).cycles
    before = pre_jump(cycles)
    assert before.max() < PRE_JUMP_LIMIT_PX[law], before
    f = norm(cycles["f"])
    t = cycles["sim_time_s"]
    # f(0) = (-120, -160) px, measured from the emulated camera's pixels (camera.model =
    # "image", the default): 0.014 px off through the default lens and noise (measured)
    assert f[0] == pytest.approx(200.0, abs=0.05)
    jumped = f[(t >= JUMP_S) & (t < JUMP_S + 0.1)]
    assert jumped.max() > 100.0, "the target jump at 3 s did not reach the controller"
    assert f[-1] == pytest.approx(s["f_final_norm"])
    assert np.all(cycles["law"] == law) and not cycles["fallback"].any()

    # the rig (CAN, zenoh, encoders, velocity filter, 60 fps camera) tracks the simulation
    t_sim, f_sim = simulate(law, DURATION_S[law])
    assert np.allclose(t_sim, t)
    gap = np.abs(f - norm(f_sim))
    # on images (the default) the frame of the jump's tick was exposed just before the jump
    # (its exposure ends at the tick's pose): the rig sees the jump one tick after the simulation
    # (analytic features), and the two differ while that period's delay is worked off
    transient = (t >= JUMP_S) & (t < JUMP_S + JUMP_TRANSIENT_S)
    gap[transient] = 0.0
    assert gap.max() < SIM_TRACKING_PX, (gap.argmax(), gap.max())
    if law == "pbc":  # the physics bound of the module docstring, in the simulation itself
        assert pre_jump({"sim_time_s": t_sim, "f": f_sim}).min() > 2.0


@pytest.mark.xfail(
    strict=True,
    raises=AssertionError,
    reason="spec vs physics: with the paper's gains PBC is at 2.2 px at t = 2.98 s even without "
    "transports (hil simulate --law pbc --duration 2.98); the issue asks < 1 px for all laws",
)
def test_pbc_below_1px_before_the_jump(lockstep_runs):
    assert pre_jump(read_log(lockstep_runs("pbc").log, raw=False).cycles).max() < 1.0


# ------------------------------------------------------------------ (b) the MCAP log, via mcap


def check_cycle_against_schema(record: dict[str, Any], schema: dict[str, Any]) -> None:
    """The subset of JSON Schema the cycle schema uses: required keys and property types
    (``null`` allowed for numbers: NaN is written as null)."""
    types = {
        "integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
        "number": lambda v: v is None or (isinstance(v, int | float) and not isinstance(v, bool)),
        "boolean": lambda v: isinstance(v, bool),
        "string": lambda v: isinstance(v, str),
        "array": lambda v: isinstance(v, list),
    }
    missing = [k for k in schema["required"] if k not in record]
    assert not missing, missing
    for key, value in record.items():
        spec = schema["properties"].get(key)
        assert spec is not None, f"field {key!r} is not in the schema"
        assert types[spec["type"]](value), (key, value, spec["type"])


@pytest.mark.parametrize("law", LAWS)
def test_mcap_log_reads_back_with_the_mcap_library(lockstep_runs, law):
    run = lockstep_runs(law)
    with run.log.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        channels = {c.topic: c for c in summary.channels.values()}
        assert set(channels) >= {CYCLE_TOPIC, CAN_RX_TOPIC, CAN_TX_TOPIC, VISION_TOPIC}
        counts = summary.statistics.channel_message_counts
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        cycles = [
            json.loads(msg.data) for _s, _c, msg in reader.iter_messages(topics=[CYCLE_TOPIC])
        ]
        vision = [json.loads(m.data) for _s, _c, m in reader.iter_messages(topics=[VISION_TOPIC])]
        can_rx = [json.loads(m.data) for _s, _c, m in reader.iter_messages(topics=[CAN_RX_TOPIC])]

    # one /controller/cycle message per tick, ticks consecutive (lockstep: tick = Sync index)
    ticks = run.summary["ticks"]
    assert counts[channels[CYCLE_TOPIC].id] == len(cycles) == ticks
    assert [c["tick"] for c in cycles] == list(range(ticks))
    assert [c["sim_time_s"] for c in cycles] == pytest.approx(np.arange(ticks) * PERIOD_S)
    assert all(c["missed_periods"] == 0 and not c["deadline_miss"] for c in cycles)

    # the schema: JSON Schema, the recorder's own, and every message conforms
    ch = channels[CYCLE_TOPIC]
    schema = summary.schemas[ch.schema_id]
    assert ch.message_encoding == "json"
    assert schema.encoding == "jsonschema" and schema.name == "hil.ControllerCycle"
    assert json.loads(schema.data) == cycle_schema()
    for record in cycles:
        check_cycle_against_schema(record, cycle_schema())
    for topic in (CAN_RX_TOPIC, CAN_TX_TOPIC, VISION_TOPIC):
        raw_schema = summary.schemas[channels[topic].schema_id]
        assert raw_schema.encoding == "jsonschema" and json.loads(raw_schema.data)["title"]

    # metadata: the configuration round-trips and is the run's; hil.run says how it ran
    assert {CONFIG_METADATA, RUN_METADATA} <= set(metadata)
    text = metadata[CONFIG_METADATA]["json"]
    cfg = config_from_json(text)
    assert isinstance(cfg, RigConfig)
    assert json.loads(cfg.to_json()) == json.loads(text)
    assert config_from_json(cfg.to_json()) == cfg
    assert cfg.controller.law == law and cfg.robot == CFG.robot and cfg.scenario == CFG.scenario
    run_info = metadata[RUN_METADATA]
    assert run_info["law"] == law and run_info["clock"] == "lockstep"
    assert float(run_info["rate_hz"]) == RATE_HZ
    assert metadata.get("hil.recorder", {}).get("dropped") == "0"

    # raw inputs as received: vision payloads decode (one answer per tick in lockstep) and the
    # CAN frames decode with the DBC
    assert len(vision) >= ticks
    decoded = [decode_features(base64.b64decode(v["data"])) for v in vision]
    assert all(d.lockstep for d in decoded) and {d.pose_seq for d in decoded} >= set(range(ticks))
    assert len(can_rx) >= ticks
    db = cantools.database.load_file(str(DBC_PATH))
    names = {db.get_message_by_frame_id(fr["arbitration_id"]).name for fr in can_rx}
    assert {"Sync", "JointPosition", "JointVelocity", "DspStatus"} <= names, names
    for fr in can_rx:
        db.decode_message(fr["arbitration_id"], bytes.fromhex(fr["data"]))
    syncs = [fr for fr in can_rx if fr["arbitration_id"] == db.get_message_by_name("Sync").frame_id]
    assert len(syncs) >= ticks

    # logread agrees with the library
    loaded = read_log(run.log)
    assert not loaded.truncated and loaded.n_cycles == ticks
    assert loaded.topic_counts[VISION_TOPIC] == len(vision)


# ------------------------------------------------------------------ (c) SIGKILL


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


# ------------------------------------------------------------------ (d) vision dropout


def tx_torques(can_tx: list[dict[str, Any]]) -> np.ndarray:
    """(Tau1, Tau2) of every TorqueCommand frame the controller sent, decoded with the DBC."""
    db = cantools.database.load_file(str(DBC_PATH))
    msg = db.get_message_by_name("TorqueCommand")
    out = [
        (d["Tau1"], d["Tau2"])
        for fr in can_tx
        if fr["arbitration_id"] == msg.frame_id
        for d in [msg.decode(bytes.fromhex(fr["data"]), decode_choices=False)]
    ]
    return np.array(out, dtype=float)


def longest_run(mask: np.ndarray) -> tuple[int, int]:
    """(start index, length) of the longest run of True."""
    best, start = (0, 0), None
    for i, v in enumerate([*mask, False]):
        if v and start is None:
            start = i
        elif not v and start is not None:
            best = max(best, (i - start, start))
            start = None
    length, first = best
    return first, length


@pytest.mark.parametrize("lockstep", [True, False], ids=["lockstep", "realtime"])
def test_vision_dropout_holds_safely_and_recovers(tmp_path, lockstep):
    log = tmp_path / "dropout.mcap"
    start_s, length_s = DROPOUT
    if not lockstep:
        start_s = REALTIME_DROPOUT_START_S
    opts = rig_options(
        log,
        law="rhc",
        lockstep=lockstep,
        duration_s=DROPOUT_DURATION_S,
        extra_vision=["--dropout", f"{start_s}:{length_s}"],
    )
    s = run_rig(opts)
    clean = assert_exit_codes(s, realtime=not lockstep)
    loaded = read_log(log)
    c = loaded.cycles
    t, stale, law = c["sim_time_s"], c["f_stale"], c["law"]

    # the controller flagged the dropout: stale ticks, all of them in hold; the summary's
    # counters are exactly the per-tick records'
    assert s["stale_features"] == int(stale.sum()) > 0
    assert s["stale_states"] == int(c["state_stale"].sum())
    if lockstep:
        assert np.all(law[stale] == "hold")
        assert np.all(law[~stale] == "rhc") and s["stale_states"] == 0
    else:
        # A busy host may make a realtime tick find the joint state late ("no_state"), or the
        # DSP's protection may have taken the torque off ("fault", "no_status", ...): the
        # controller then commands zero torque. Under any scheduling: the law never acts on
        # stale features, and every tick is the law, the hold damper, or zero torque.
        assert not np.any(law[stale] == "rhc")
        zero = ~np.isin(law, ["rhc", "hold"])
        assert set(law[zero]) <= ZERO_TORQUE_MODES, set(law[zero])
        assert np.all(c["tau"][zero] == 0.0)
        assert np.all(law[c["state_stale"].astype(bool)] != "rhc")
    expected = (length_s - FEATURE_TIMEOUT_S) / PERIOD_S  # 20 ticks
    if lockstep:  # deterministic: exactly the window, once the last frame aged past the timeout
        first, n = longest_run(stale)
        assert n == stale.sum() and expected - 1 <= n <= expected + 1, n
        # on images (camera.model = "image", the default) a frame is stamped at the middle of its
        # exposure, camera.exposure_s / 2 before its period's pose: the last frame before the
        # window goes stale up to one tick earlier than an analytic frame stamped at the pose
        lo = start_s + FEATURE_TIMEOUT_S - PERIOD_S
        assert lo - 1e-9 <= t[first] <= start_s + FEATURE_TIMEOUT_S + 0.05
        assert t[first + n - 1] < start_s + length_s
    else:
        # realtime: where and how long the stale stretch is depends on the host's scheduling
        # (the window is on the vision process's clock, and a busy host adds stale stretches of
        # its own, vision frames delayed > 100 ms in transit); what holds under any scheduling
        # is checked: every stale tick is in hold (above), and the longest stale stretch, the
        # dropout's, is held safely (below). Its timing is reported only.
        first, n = longest_run(stale)
        print(
            f"realtime dropout: longest stale stretch {n} ticks from controller t = "
            f"{t[first]:.2f} s ({expected:g} expected); {int(stale.sum())} stale ticks in all, "
            f"{s['stale_states']} without a fresh joint state"
        )
        assert n >= 1
    assert c["f_valid"][stale].all()  # the controller still holds the last valid (old) frame
    assert (c["f_age_ms"][stale] > FEATURE_TIMEOUT_S * 1e3).all()

    # no NaN ever sent: the logged commands and the TorqueCommand frames on the bus
    tau = c["tau"]
    assert np.isfinite(tau).all()
    sent = tx_torques(loaded.can_tx)
    assert len(sent) >= len(tau) and np.isfinite(sent).all()
    # the arm is safe: torque within the amplifier limits, velocities bounded, and in hold the
    # pure damper tau = -2 R dq only takes energy out
    assert (np.abs(tau) <= TAU_MAX + 1e-9).all() and (np.abs(sent) <= TAU_MAX + 0.01).all()
    dq = c["dq"]
    assert np.isfinite(dq).all()
    if lockstep:  # deterministic: the scenario's own bound
        assert np.abs(dq).max() < DQ_LIMIT
    elif clean:  # in real time the bound that holds under any scheduling: the DSP's limits
        assert np.all(np.abs(dq) <= np.array(CFG.dsp.dq_max)), np.abs(dq).max(axis=0)
    else:  # a loop stalled by the host may excite joint 2; the DSP's velocity limit caught it
        dq_max = np.array(CFG.dsp.dq_max)
        if np.any(np.abs(dq) > dq_max):
            assert "velocity_limit" in s["dsp_faults"], s["dsp_faults"]
        print(f"realtime, not clean: max |dq| {np.abs(dq).max(axis=0)} (DSP limit {dq_max})")
    hold = slice(first, first + n)
    acted = c["dq_pred"]  # the velocity the hold acted on: dq brought up to the tick (NaN in
    acted = np.where(np.isfinite(acted), acted, 0.0)  # a tick where the drive was off: tau 0)
    assert np.all(tau[hold] * acted[hold] <= 1e-12), "hold torque must oppose the motion"
    if clean:  # the damper alone acted throughout (no fault let the arm coast)
        assert np.linalg.norm(dq[first + n - 1]) <= np.linalg.norm(dq[first]) + 0.05

    # after the features return the law takes over again and converges (in real time: when the
    # DSP's protection did not have to take the torque off on a busy host)
    after = law[first + n :]
    if lockstep:
        assert np.all(after == "rhc")
    elif clean or not s["dsp_faults"]:  # fresh features again (stale/no_state ticks held above)
        assert np.any(after == "rhc"), "features did not return"
    else:  # a DSP fault is latched: from the first fault tick on, the law never runs again
        faulted = np.flatnonzero(law == "fault")
        assert faulted.size and not np.any(law[faulted[0] :] == "rhc"), sorted(set(law))
    if clean:
        assert s["f_final_norm"] < 1.0, s["f_final"]
        assert norm(c["f"])[-1] < 1.0


# ------------------------------------------------------------------ (e) the CLI and failures


def test_hil_up_json_from_the_command_line(tmp_path):
    ep = free_endpoint()
    log = tmp_path / "cli.mcap"
    args = ["up", "--lockstep", "--duration", "2", "--json", "--law", "ioc"]
    args += ["--can", isolated_spec("udp_multicast"), "--zenoh-endpoint", ep, "--log", str(log)]
    try:
        done = run_hil(args, 120)
    finally:
        assert_nothing_left(ep)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    for key in ("J", "f_final", "ticks", "deadline_misses", "solve_us_p99", "log"):
        assert key in summary, key
    assert summary["ticks"] == 100 and summary["log"] == str(log) and log.exists()
    assert len(summary["f_final"]) == 2 and math.isfinite(summary["J"])
    assert summary["exit_codes"] == {"controller": 0, "vision": 0, "emulator": 0}
    assert read_log(log, raw=False).n_cycles == 100


def test_hil_up_reports_a_process_that_cannot_start(tmp_path):
    """A bad CAN spec: the emulator (or controller) exits 2; ``hil up`` names it with its exit
    status and stderr tail, exits non-zero, and leaves nothing running."""
    ep = free_endpoint()
    args = ["up", "--lockstep", "--duration", "2", "--json", "--can", "udp_multicast:nowhere:1"]
    args += ["--zenoh-endpoint", ep, "--log", str(tmp_path / "bad.mcap")]
    try:
        done = run_hil(args, 120)
    finally:
        assert_nothing_left(ep)
    assert done.returncode == 2, (done.stdout, done.stderr)
    err = done.stderr
    assert err.startswith("hil up: error:"), err
    m = re.search(r"(emulator|vision|controller) exited with status (-?\d+)", err)
    assert m and m.group(2) == "2", err
    assert f"hil {m.group(1)}: error:" in err  # the stderr tail of the process that died
    assert not done.stdout.strip().startswith("{")


def test_run_rig_reports_an_emulator_killed_mid_run(tmp_path):
    log = tmp_path / "emu-killed.mcap"
    opts = rig_options(log, law="ioc", lockstep=True, duration_s=600.0)
    with Rig(opts) as rig:
        rig.start()
        children = list(rig.children)
        wait_for_cycles(log, 50, rig)
        emu = next(c for c in rig.children if c.name == "emulator")
        os.kill(emu.proc.pid, signal.SIGKILL)
        with pytest.raises(RigProcessError) as info:
            rig.wait_controller()
        message = str(info.value)
        assert message.startswith("emulator killed by SIGKILL"), message
        assert info.value.end.name == "emulator" and info.value.end.returncode == -signal.SIGKILL
        assert "hil emulator: serving the arm on" in message  # its stderr tail
    # the context manager stopped the others; the conftest fixture checks for leaks as well
    assert len(children) == 3 and all(c.proc.returncode is not None for c in children)
    assert_nothing_left(opts.zenoh_endpoint)
    loaded = read_log(log)  # the controller was stopped with SIGTERM: a finished file
    assert loaded.n_cycles >= 50 and not loaded.truncated


def test_run_rig_bad_spec_raises_naming_the_process(tmp_path):
    opts = rig_options(tmp_path / "x.mcap", can="nosuchbus:0", lockstep=True, duration_s=2.0)
    with pytest.raises(RigProcessError, match=r"(emulator|controller) exited with status 2"):
        run_rig(opts)
    assert_nothing_left(opts.zenoh_endpoint)


def test_a_dsp_sampling_after_the_release_gets_its_states_compensated(tmp_path):
    """Real daemons, real time, a DSP that samples 1 ms after the controller's release
    (``dsp.state_lead_us`` = a period less 1 ms): every tick reads a state about 19 ms old
    (fault injection: without compensation, three runs of three ended in a velocity-limit
    fault). What holds under any scheduling: each tick that ran the law compensated the age it
    measured (``predict_ms`` = ``state_age_ms``, and ``f_predict_ms`` = ``f_age_ms``), the law
    acted on a state other than the measured one, and the log replays exactly."""
    from rt_controller.logtools.replay import replay_log

    rig = tmp_path / "rig.toml"
    rig.write_text("[dsp]\nstate_lead_us = 19000.0\n")
    log = tmp_path / "lag.mcap"
    s = run_rig(rig_options(log, law="ioc", config=str(rig), duration_s=3.0))
    assert_exit_codes(s, realtime=True)
    c = read_log(log, raw=False).cycles
    ran = np.asarray(c["law"]) == "ioc"
    age, predicted = np.asarray(c["state_age_ms"])[ran], np.asarray(c["predict_ms"])[ran]
    assert ran.sum() > 50
    assert np.array_equal(predicted, np.where(age > 0, age, 0.0))
    assert np.median(predicted) > 10.0  # most ticks ran on the previous period's sample
    moved = np.any(np.asarray(c["q_pred"])[ran] != np.asarray(c["q"])[ran], axis=1)
    assert moved[1:][predicted[1:] > 10.0].all()  # (at the first, the arm rests, no torque yet)
    f_age, f_predicted = np.asarray(c["f_age_ms"])[ran], np.asarray(c["f_predict_ms"])[ran]
    assert np.array_equal(f_predicted, np.where(f_age > 0, f_age, 0.0))  # the features too
    result = replay_log(log)
    assert result.ok and result.max_abs_dtau <= 1e-9
