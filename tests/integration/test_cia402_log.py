"""A real cia402 run's log (the three processes, lockstep, 1 s): its raw CANopen frames are
in ``/hal/can/tx`` and ``/hal/can/rx`` from the boot on, decode as the profile's traffic, the
recorder's ``/hal/canopen`` holds each of them decoded, and ``hil report`` has the CANopen
section (SYNC jitter, SYNC to TPDO, PDO round trip, torque to effect, EMCYs) computed from
them."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from hal.bus import isolated_spec
from hal.config import load_config
from hal.zenoh_session import free_loopback_port
from rt_controller.config_rules import config_toml
from rt_controller.logtools.canopen_timing import decoded_frames
from rt_controller.logtools.deadline_report import summarize
from rt_controller.logtools.reader import read_log
from rt_controller.rig.options import RigOptions
from rt_controller.rig.processes import run_rig
from rt_controller.runtime.record_encoding import CANOPEN_SCHEMA, canopen_dict
from rt_controller.runtime.recorder import CAN_RX_TOPIC, CAN_TX_TOPIC, CANOPEN_TOPIC

pytestmark = pytest.mark.integration


def _run(work):
    cfg = load_config(None).with_overrides({"hardware.profile": "cia402"})
    conf = work / "rig.toml"
    conf.write_text(config_toml(cfg))
    log = work / "run.mcap"
    summary = run_rig(
        RigOptions(
            config=str(conf),
            law="ioc",
            duration_s=1.0,
            lockstep=True,
            log=log,
            can=isolated_spec("udp_multicast"),
            zenoh_endpoint=f"tcp/127.0.0.1:{free_loopback_port()}",
        )
    )
    assert not summary.get("problems"), summary
    return cfg, log, summary


@pytest.fixture(scope="module")
def cia402_log(tmp_path_factory):
    return _run(tmp_path_factory.mktemp("cia402-log"))


def test_the_log_holds_every_canopen_frame_from_the_boot_on(cia402_log):
    cfg, log, summary = cia402_log
    loaded = read_log(log)
    frames = decoded_frames(loaded.can_rx, loaded.can_tx)
    kinds = {(f.direction, f.kind) for f in frames}
    for want in (
        ("tx", "nmt"),
        ("tx", "sdo_request"),
        ("rx", "sdo_response"),
        ("rx", "heartbeat"),
        ("tx", "sync"),
        ("tx", "rpdo1"),
        ("rx", "tpdo1"),
        ("rx", "tpdo2"),
    ):
        assert want in kinds, sorted(kinds)
    assert not [f for f in frames if "error" in f.fields]
    nodes = {cfg.cia402.node_id_1, cfg.cia402.node_id_2}
    assert {f.node for f in frames if f.kind == "tpdo1"} == nodes
    # every SYNC of the run is there (arming and deactivation send some more)
    syncs = sum(1 for f in frames if f.kind == "sync")
    assert syncs >= summary["ticks"], (syncs, summary["ticks"])


def _topics_in_file_order(log) -> list[tuple[str, dict]]:
    from mcap.reader import make_reader

    topics = (CAN_RX_TOPIC, CAN_TX_TOPIC, CANOPEN_TOPIC)
    with open(log, "rb") as fh:
        messages = make_reader(fh).iter_messages(topics=topics, log_time_order=False)
        return [(ch.topic, json.loads(m.data)) for _s, ch, m in messages]


def test_the_decoded_topic_agrees_with_the_raw_frames_one_for_one(cia402_log):
    """Lockstep loses nothing: every raw frame has its ``/hal/canopen`` record right after it
    in the file, decoded as :func:`canopen_dict` decodes the raw record; the run's summary
    counts as many decoded frames as raw ones."""
    _cfg, log, summary = cia402_log
    messages = _topics_in_file_order(log)
    raw = [(t, m) for t, m in messages if t != CANOPEN_TOPIC]
    decoded = [m for t, m in messages if t == CANOPEN_TOPIC]
    assert raw and len(decoded) == len(raw)
    for (topic, frame), (topic2, record) in zip(messages[::2], messages[1::2], strict=True):
        assert topic2 == CANOPEN_TOPIC, (topic, topic2)
        direction = "rx" if topic == CAN_RX_TOPIC else "tx"
        assert record == canopen_dict(direction, frame)
        assert (record["t_ns"], record["cob_id"], record["data"]) == (
            frame["t_ns"],
            frame["arbitration_id"],
            frame["data"],
        )
    rec = summary["recorder"]
    assert rec[CANOPEN_TOPIC] == rec[CAN_RX_TOPIC] + rec[CAN_TX_TOPIC] == len(decoded)
    assert rec["dropped"] == 0 and rec["encode_errors"] == 0


def test_the_decoded_topic_holds_the_boot_the_syncs_and_both_nodes_pdos(cia402_log):
    import jsonschema

    cfg, log, summary = cia402_log
    records = read_log(log).canopen
    for rec in records:
        jsonschema.validate(rec, CANOPEN_SCHEMA)
    assert not [r for r in records if "error" in r]
    nodes = {cfg.cia402.node_id_1, cfg.cia402.node_id_2}

    def where(direction: str, kind: str) -> list[dict]:
        return [r for r in records if (r["direction"], r["kind"]) == (direction, kind)]

    boot = where("tx", "nmt")[0]["fields"]
    assert boot["command"] == "reset communication", boot
    assert {r["node"] for r in where("rx", "heartbeat")} == nodes  # boot-up, then heartbeats
    written = {(r["node"], r["fields"].get("index")) for r in where("tx", "sdo_request")}
    for node in nodes:  # the boot's SDO writes, on every drive
        assert {(node, i) for i in (0x1017, 0x1016, 0x60C2, 0x6072, 0x6060)} <= written
    mode = {  # 0x6061 read back: the last answer of each drive is CST
        r["node"]: r["fields"]["sdo_value"]
        for r in where("rx", "sdo_response")
        if r["fields"].get("index") == 0x6061 and "sdo_value" in r["fields"]
    }
    assert mode == dict.fromkeys(nodes, 10), mode
    assert not [r for r in where("rx", "sdo_response") if "abort_code" in r["fields"]]
    assert len(where("tx", "sync")) >= summary["ticks"]
    for kind, direction, field in (
        ("rpdo1", "tx", "target_torque"),
        ("tpdo1", "rx", "statusword"),
        ("tpdo2", "rx", "torque_actual"),
    ):
        frames = where(direction, kind)
        assert {r["node"] for r in frames} == nodes, kind
        assert all(isinstance(r["fields"][field], int) for r in frames), kind
    states = {r["fields"]["state"] for r in where("rx", "tpdo1")}
    assert "OPERATION ENABLED" in states and "FAULT" not in states, states


def _bus_of_the_ticks(log) -> list[dict]:
    """The decoded frames from the boot to the end of the run's last tick, without their
    times and the drives' heartbeats (both follow the wall clock, not the SYNCs)."""
    loaded = read_log(log)
    end = int(loaded.cycles["t_ns"][-1])
    return [
        {k: v for k, v in r.items() if k != "t_ns"}
        for r in loaded.canopen
        if r["t_ns"] <= end and r["kind"] != "heartbeat"
    ]


def test_the_decoded_topic_is_the_same_in_a_second_lockstep_run(cia402_log, tmp_path):
    """Lockstep is deterministic, and so is what the recorder decodes: a second run gives the
    same frames (boot, arming, every period's RPDOs, SYNCs and TPDOs) with the same values."""
    _cfg, log, _summary = cia402_log
    _cfg2, log2, _summary2 = _run(tmp_path)
    first, second = _bus_of_the_ticks(log), _bus_of_the_ticks(log2)
    assert len(first) > 100 and first == second


def test_report_times_sync_and_pdos_and_lists_no_emcy(cia402_log):
    cfg, log, summary = cia402_log
    co = summarize(read_log(log))["canopen"]
    assert co is not None
    # lockstep: one SYNC per tick after period 0, each answered by both drives
    assert co["sync"]["syncs"] == summary["ticks"] - 1, co["sync"]
    assert co["answered"] == co["sync"]["syncs"] and co["incomplete"] == 0, co
    for key in ("sync_to_tpdo_us", "pdo_round_trip_us", "torque_to_effect_us"):
        assert co[key]["median"] > 0, (key, co[key])
    assert co["sync_to_tpdo_us"]["median"] <= co["pdo_round_trip_us"]["median"]
    assert co["changes"] > 0 and co["never"] == 0, co  # the law's torques took effect
    assert co["emcys"] == []
    nodes = {str(cfg.cia402.node_id_1), str(cfg.cia402.node_id_2)}
    assert set(co["drive_states"]) == nodes, co["drive_states"]
    for states in co["drive_states"].values():
        assert "OPERATION ENABLED" in states and "FAULT" not in states, states


def test_hil_report_prints_the_canopen_section(cia402_log):
    _cfg, log, _summary = cia402_log
    text = subprocess.run(
        [sys.executable, "-m", "rt_controller.cli", "report", str(log)],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert "CANopen (cia402)" in text and "EMCY: none" in text, text
    out = subprocess.run(
        [sys.executable, "-m", "rt_controller.cli", "report", "--json", str(log)],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert json.loads(out)["canopen"]["answered"] > 0


def test_each_tick_records_the_drives_states_and_pdo_values(cia402_log):
    """The cycle record's ``drive_*`` fields (Foxglove plots them from /controller/cycle):
    the power states while the law runs, and, in lockstep, the torque actual each tick read
    is the target torque of the RPDO its SYNC latched."""
    import jsonschema
    from mcap.reader import make_reader

    from rt_controller.runtime.recorder import CYCLE_TOPIC, cycle_schema

    _cfg, log, _summary = cia402_log
    with open(log, "rb") as fh:
        records = [json.loads(m.data) for _s, _c, m in make_reader(fh).iter_messages([CYCLE_TOPIC])]
    schema = cycle_schema()
    for rec in records:
        jsonschema.validate(rec, schema)
    ran = [r for r in records if r["law"] == "ioc"]
    enabled = ("OPERATION ENABLED", "OPERATION ENABLED")
    assert ran and all((r["drive_state_1"], r["drive_state_2"]) == enabled for r in ran)
    assert all(w & 0x6F == 0x27 for r in ran for w in r["drive_statusword"])  # enabled
    assert all(r["drive_controlword"] == [0x0F, 0x0F] for r in ran)
    assert any(r["drive_target_torque"] != [0, 0] for r in ran)
    for r in ran:
        assert r["drive_torque_actual"] == r["drive_target_torque"], r
    syncs = [r["drive_sync"] for r in ran]
    assert syncs == list(range(syncs[0], syncs[0] + len(syncs)))  # one SYNC per tick


def test_the_analysis_api_decodes_a_cia402_logs_frames_by_cob_id(cia402_log, tmp_path):
    pytest.importorskip("pandas")
    from rt_controller.logs import load

    cfg, log, _summary = cia402_log
    df = load(log).can_frames
    assert {"nmt", "sync", "rpdo1", "tpdo1", "tpdo2", "heartbeat"} <= set(df["message"])
    tpdo1 = df[df["message"] == "tpdo1"]
    assert set(tpdo1["node"]) == {cfg.cia402.node_id_1, cfg.cia402.node_id_2}
    assert "OPERATION ENABLED" in set(tpdo1["state"])
    assert "decode_error" not in df.columns
    pytest.importorskip("pyarrow")
    from rt_controller.logs.export import export, plan_outputs

    # every table of the log exports: one type per column (the profile's diagnostics hold
    # lists and dicts: their JSON text)
    files = plan_outputs(log, "parquet", ("cycle", "diagnostics", "can"), tmp_path)
    written = export(load(log), "parquet", files)
    assert len(written) == 3 and all(p.stat().st_size > 0 for p in files.values())
