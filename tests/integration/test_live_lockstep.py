"""The live service end to end in lockstep, natively: ``hil up`` (emulator, vision, controller
as separate processes) over CAN on ``udp_multicast`` and zenoh on loopback, and its MCAP log.

Every run gets its own CAN port (:func:`hal.bus.isolated_spec`) and zenoh port, so parallel runs
and other rigs on the host never meet. Lockstep runs are deterministic and faster than real time
(realtime runs, where the claim is about wall-clock behaviour: ``test_live_sigkill.py``,
``test_live_stale_inputs.py``). No timing is asserted (that is ``hil bench``'s job).

What is checked (issue 5, "Tests"; one lockstep run per law, shared by the module's tests):

* the paper scenario in lockstep with each law: |f| below 1 px just before the t = 3 s target
  jump and again at the end, and the HIL run tracks the transport-free simulation
  (:func:`rt_controller.control.simulate.run_closed_loop` on the emulator's physics) tick by tick;
* the MCAP log reads back with the ``mcap`` library itself: one ``/controller/cycle`` message per
  tick, JSON Schema present, ``hil.config`` / ``hil.run`` metadata, raw CAN and vision messages.

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
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cantools
import numpy as np
import pytest
from mcap.reader import make_reader

from hal.can_database import DBC_PATH
from hal.config import RigConfig, config_from_json
from hal.vision_codec import decode_features
from rt_controller.logtools.reader import read_log
from rt_controller.rig.processes import run_rig
from rt_controller.runtime.recorder import (
    CAN_RX_TOPIC,
    CAN_TX_TOPIC,
    CONFIG_METADATA,
    CYCLE_TOPIC,
    RUN_METADATA,
    VISION_TOPIC,
    cycle_schema,
)
from tests.support.live_rig import CFG, PERIOD_S, RATE_HZ, norm, rig_options

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

LAWS = ("pbc", "ioc", "rhc")
JUMP_S = 3.0
"""The paper scenario's target jump (3 s, ScenarioConfig.jump_time)."""

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


def pre_jump(cycles: dict[str, np.ndarray]) -> np.ndarray:
    """|f| at the ticks just before the disturbance: sim time in [2.9, 3.0)."""
    t = cycles["sim_time_s"]
    sel = (t >= JUMP_S - 0.1 - 1e-9) & (t < JUMP_S - 1e-9)
    assert sel.sum() == 5, t
    return norm(cycles["f"][sel])


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
