"""Logs as data: ``rt_controller.logs.load`` against the raw MCAP read with ``mcap`` alone,
``hil export`` read back (csv module, pyarrow, scipy.io.loadmat), ``hil info`` on a clean log, a
truncated one and MCAP files hil did not write, and the core without pandas.

The logs are written through the recorder's public seam (:class:`CycleRecorder`, the records
built by :func:`cycle_record` and :func:`diagnostics.build`, the frames by hal's codecs), in the
daemon's shapes: a hold tick without features, a tick without joint state, deadline misses, an
unknown CAN id, a frame too short to decode, periodic and final diagnostics.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import sys
from pathlib import Path

import can
import cantools
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from hal.can_codec import ControllerCodec, DspCodec
from hal.can_database import DBC_PATH
from hal.config import RigConfig
from rt_controller.cli import main
from rt_controller.errors import LogError, MissingExtraError
from rt_controller.logs import load
from rt_controller.runtime import diagnostics
from rt_controller.runtime.cycle_record import Timing, cycle_record
from rt_controller.runtime.recorder import CycleRecorder

TICKS = 60
PERIOD_NS = 20_000_000
T0_NS = 7_000_000_000
NO_STATE = 20
MISSES = (33, 47)
DIAG_EVERY = 25
UNKNOWN_ID = 0x7F0
N_FRAMES = TICKS + 2 * (TICKS - 1) + 2 + TICKS
"""Sync, JointPosition + JointVelocity (not at NO_STATE), two odd frames, TorqueCommand."""
INSTALL = "pip install 'hil-rhc-visual-servo[analysis]'"


def decision(k: int) -> dict:
    """Decision fields of tick ``k`` (tick 0 holds: no features yet)."""
    if k == 0:
        nan2 = [math.nan, math.nan]
        return {
            "q_pred": [0.5, -0.5], "dq_pred": [0.0, 0.0], "f_pred": nan2, "xi": [0.0, 0.0],
            "u": [0.0, 0.0], "tau": [0.0, 0.0], "tau_saturated": False, "law": "hold",
            "residual": 0.0, "iterations": 0, "fallback": False, "cost": math.nan, "V": math.nan,
        }  # fmt: skip
    return {
        "q_pred": [0.5 + k / 1e3, -0.5], "dq_pred": [k / 1e2, -k / 1e2],
        "f_pred": [-120.0 + k, -160.0 + 2 * k], "xi": [0.1 * k, -0.2 * k],
        "u": [math.sin(k), math.cos(k)], "tau": [math.sin(k) / 3, 1 / (k + 1)],
        "tau_saturated": k % 9 == 0, "law": "ioc", "residual": 1e-6 * k,
        "iterations": k % 4, "fallback": k == 13, "cost": 0.25 * k, "V": 1.0 / k,
    }  # fmt: skip


def diag(k: int, misses: int, final: bool, watchdog_trips: int, disarmed: int) -> dict:
    return diagnostics.build(
        t_ns=T0_NS + k * PERIOD_NS + 1_000,
        tick=k,
        can_rx={"accepted": 3 * k, "unknown_id": 1 if k > 5 else 0, "bad_mac": 0, "rejected": 0},
        features={"received": k, "accepted": k, "bad_mac": 0, "rejected": 0},
        dsp={
            "status_received": True,
            "mode": "enabled",
            "torque_enabled": True,
            "watchdog_tripped": False,
            "rejected_frames": 0,
            "events.enabled": 1,
            **({"ticks.disarmed": disarmed} if disarmed else {}),
        },
        controller={"ticks": k, "deadline_misses": misses, "watchdog_trips": watchdog_trips},
        recorder={"written": 4 * k, "dropped": 0, "encode_errors": 0, "pending": 7},
        final=final,
    )


def record(
    path: Path,
    ticks: int = TICKS,
    *,
    watchdog_trips: int = 0,
    disarmed: int = 0,
    chunk=4096,
    final: bool = True,
) -> Path:
    """A daemon-shaped log of ``ticks`` ticks (see the module docstring); ``final=False``: no
    final /diagnostics record (the controller killed, its recorder closing the file)."""
    cfg = RigConfig().with_overrides({"controller.law": "ioc"})
    dsp, own = DspCodec(), ControllerCodec()
    info = {"clock": "lockstep", "can": "virtual", "zenoh": "tcp/127.0.0.1:1", "recorder": "thread"}
    misses = 0
    with CycleRecorder(path, cfg, run_info=info, chunk_size=chunk) as rec:
        for k in range(ticks):
            wake = T0_NS + k * PERIOD_NS
            rec.record_can(dsp.encode_sync(k), wake - 30_000, "rx")
            q, dq = [0.5 + k / 1e3, -0.5], [k / 1e2, -k / 1e2]
            if k != NO_STATE:
                for msg in dsp.encode_state(q, dq, k % 16):
                    rec.record_can(msg, wake - 20_000, "rx")
            if k == 5:
                rec.record_can(can.Message(arbitration_id=UNKNOWN_ID, data=b"\1\2"), wake, "rx")
                rec.record_can(can.Message(arbitration_id=0x100, data=b"\1\2\3"), wake, "rx")
            miss = k in MISSES
            misses += miss
            d = decision(k)
            rec.record_cycle(
                cycle_record(
                    tick=k,
                    t_ns=wake,
                    sim_time_s=k * PERIOD_NS / 1e9,
                    timing=Timing(
                        lateness_us=25_000.0 if miss else float(k % 7),
                        read_us=3.0 + k,
                        solve_us=40.5,
                        write_us=5.0,
                        cycle_us=21_000.0 if miss else 90.0,
                        e2e_us=math.nan if k == NO_STATE else 60.0 + k,
                        deadline_miss=miss,
                        missed_periods=1 if miss else 0,
                    ),
                    q=[math.nan, math.nan] if k == NO_STATE else q,
                    dq=[0.0, 0.0] if k == NO_STATE else dq,
                    f=[math.nan, math.nan] if k == 0 else [-120.0 + k, -160.0 + 2 * k],
                    f_age_ms=math.nan if k == 0 else 4.0,
                    state_age_ms=0.5,
                    f_valid=k != 0,
                    f_stale=k == 0,
                    state_stale=k == NO_STATE,
                    decision=d,
                    predict_ms=0.0,
                    f_predict_ms=0.25 * (k % 2),
                )
            )
            rec.record_can(own.encode_torque(*d["tau"], tick=k), wake + 50_000, "tx")
            last = k == ticks - 1
            if k % DIAG_EVERY == 0 or last:
                rec.record_diagnostics(diag(k, misses, False, watchdog_trips, disarmed))
            if last and final:
                final_diag = diag(k + 1, misses, True, watchdog_trips, disarmed)
                rec.record_diagnostics(final_diag, final=True)
    return path


@pytest.fixture(scope="module")
def log_path(tmp_path_factory) -> Path:
    return record(tmp_path_factory.mktemp("logs") / "run.mcap")


def raw_messages(path: Path, topic: str) -> list[dict]:
    """Every message of ``topic`` decoded with json, read with mcap's reader alone."""
    with path.open("rb") as fh:
        return [json.loads(m.data) for _, _, m in make_reader(fh).iter_messages(topics=[topic])]


def raw_counts(path: Path) -> dict[str, int]:
    with path.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        stats = summary.statistics.channel_message_counts
        return {ch.topic: stats.get(cid, 0) for cid, ch in summary.channels.items()}


def columns_of(field: str, value: list) -> list[str]:
    """The documented column names of a vector field (independent of the implementation)."""
    if field in ("f", "f_pred"):
        return [f"{field}_x", f"{field}_y"]
    return [f"{field}{j + 1}" for j in range(len(value))]


def same(a, b) -> bool:
    """Equal values, None/NaN on either side meaning missing."""
    missing = [x is None or (isinstance(x, float) and math.isnan(x)) for x in (a, b)]
    if any(missing):
        return all(missing)
    if isinstance(a, bool) or isinstance(b, bool):
        return bool(a) == bool(b)
    return a == b


def scalar(x):
    return x.item() if isinstance(x, np.generic) else x


# ----------------------------------------------------------------------------- load()


def test_load_gives_every_field_of_every_cycle(log_path):
    raw = raw_messages(log_path, "/controller/cycle")
    run = load(log_path)
    df, arrays = run.cycles, run.arrays()
    assert len(raw) == TICKS and list(df.index) == [r["tick"] for r in raw]
    assert df.index.name == "tick"
    expected: set[str] = set()
    for i, rec in enumerate(raw):
        for field, value in rec.items():
            if field == "tick":
                continue
            names = columns_of(field, value) if isinstance(value, list) else [field]
            values = value if isinstance(value, list) else [value]
            expected.update(names)
            for name, v in zip(names, values, strict=True):
                got = scalar(df[name].iloc[i])
                assert same(got, v), (rec["tick"], name, got, v)
                assert same(scalar(arrays[name][i]), v), (rec["tick"], name)
    assert set(df.columns) == expected
    assert {"q1", "q2", "dq1", "dq2", "f_x", "f_y", "tau1", "tau2", "sim_time_s"} <= expected


def test_load_gives_diagnostics_config_and_metadata(log_path):
    run = load(log_path)
    raw = raw_messages(log_path, "/diagnostics")
    d = run.diagnostics
    assert len(d) == len(raw) == 5 and list(d["tick"]) == [r["tick"] for r in raw]
    assert list(d["final"]) == [r["final"] for r in raw]
    for i, rec in enumerate(raw):
        for status in rec["status"]:
            assert d[f"{status['name']}_level"].iloc[i] == status["level"]
            assert d[f"{status['name']}_message"].iloc[i] == status["message"]
            for key, value in status["values"].items():
                assert same(scalar(d[f"{status['name']}_{key.replace('.', '_')}"].iloc[i]), value)
    assert d["time_s"].iloc[0] == pytest.approx(1e-6)  # 1 us after the first tick's wake-up
    assert run.config == RigConfig().with_overrides({"controller.law": "ioc"})
    assert run.config_dict == json.loads(run.config_json)
    assert (
        run.config_digest == "sha256:" + hashlib.sha256(run.config.to_json().encode()).hexdigest()
    )
    assert run.info["can"] == "virtual" and not run.truncated


def test_can_frames_are_decoded_with_the_dbc(log_path):
    db = cantools.database.load_file(str(DBC_PATH))
    raw = [("rx", f) for f in raw_messages(log_path, "/hal/can/rx")]
    raw += [("tx", f) for f in raw_messages(log_path, "/hal/can/tx")]
    raw.sort(key=lambda x: x[1]["t_ns"])
    frames = load(log_path).can_frames
    assert len(frames) == len(raw) == N_FRAMES
    assert list(frames["t_ns"]) == [f["t_ns"] for _, f in raw]
    assert list(frames["direction"]) == [d for d, _ in raw]
    assert list(frames["frame_id"]) == [f["arbitration_id"] for _, f in raw]
    for i, (_, f) in enumerate(raw):
        row = frames.iloc[i]
        assert row["data"] == f["data"]
        if f["arbitration_id"] == UNKNOWN_ID:
            assert row["message"] is None or row["message"] != row["message"]  # None / NaN
            continue
        msg = db.get_message_by_frame_id(f["arbitration_id"])
        assert row["message"] == msg.name
        if len(f["data"]) // 2 < msg.length:
            assert "decode_error" in frames.columns and isinstance(row["decode_error"], str)
            continue
        for name, value in msg.decode(bytes.fromhex(f["data"]), decode_choices=False).items():
            assert row[name] == value, (i, msg.name, name)
    torque = frames[(frames["message"] == "TorqueCommand") & (frames["direction"] == "tx")]
    assert np.allclose(torque["Tau1"], load(log_path).cycles["tau1"], atol=0.005)
    assert set(frames["message"].dropna()) >= {"Sync", "JointPosition", "JointVelocity"}


def test_without_pandas_numpy_still_works_and_dataframes_name_the_extra(log_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pandas", None)  # `import pandas` raises ImportError
    run = load(log_path)
    assert run.arrays()["f_x"][1] == -119.0 and run.arrays("can")["message"][0] == "Sync"
    with pytest.raises(MissingExtraError, match=INSTALL.replace("[", r"\[").replace("]", r"\]")):
        _ = run.cycles
    assert main(["export", str(log_path), "--format", "csv"]) == 2


# ------------------------------------------------------------------------------ export


def test_export_csv_read_back_with_the_csv_module(log_path, tmp_path, capsys):
    assert main(["export", str(log_path), "--format", "csv", "--out", str(tmp_path)]) == 0
    assert "cycle: 60 rows" in capsys.readouterr().out
    raw = raw_messages(log_path, "/controller/cycle")
    with (tmp_path / "run.cycle.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == TICKS
    for rec, row in zip(raw, rows, strict=True):
        for field, value in rec.items():
            names = columns_of(field, value) if isinstance(value, list) else [field]
            values = value if isinstance(value, list) else [value]
            for name, v in zip(names, values, strict=True):
                text = row[name]
                if v is None:
                    assert text == "", (name, text)
                elif isinstance(v, bool):
                    assert text == str(v)
                elif isinstance(v, str):
                    assert text == v
                else:
                    assert float(text) == v, (rec["tick"], name)
    for topic, n in (("diagnostics", 5), ("can", N_FRAMES)):
        with (tmp_path / f"run.{topic}.csv").open(newline="") as fh:
            assert len(list(csv.DictReader(fh))) == n


def test_export_parquet_read_back_with_pyarrow(log_path, tmp_path, capsys):
    import pyarrow.parquet as pq

    out = tmp_path / "cycles.parquet"
    argv = ["export", str(log_path), "--format", "parquet", "--topics", "cycle", "--out", str(out)]
    assert main([*argv, "--json"]) == 0
    files = json.loads(capsys.readouterr().out)["files"]
    assert files == [{"topic": "cycle", "path": str(out), "rows": TICKS}]
    table = pq.read_table(out)
    assert json.loads(table.schema.metadata[b"hil.config"])["controller"]["law"] == "ioc"
    cols = table.to_pydict()
    for i, rec in enumerate(raw_messages(log_path, "/controller/cycle")):
        for field, value in rec.items():
            names = columns_of(field, value) if isinstance(value, list) else [field]
            values = value if isinstance(value, list) else [value]
            for name, v in zip(names, values, strict=True):
                assert same(cols[name][i], v), (rec["tick"], name)
    argv = ["export", str(log_path), "--format", "parquet", "--out", str(tmp_path)]
    assert main(argv) == 0
    frames = pq.read_table(tmp_path / "run.can.parquet").to_pydict()
    assert frames["message"][:2] == ["Sync", "JointPosition"] and UNKNOWN_ID in frames["frame_id"]
    assert pq.read_table(tmp_path / "run.diagnostics.parquet").num_rows == 5


def test_export_mat_read_back_with_scipy(log_path, tmp_path, capsys):
    from scipy.io import loadmat

    assert main(["export", str(log_path), "--format", "mat", "--out", str(tmp_path)]) == 0
    capsys.readouterr()
    mat = loadmat(tmp_path / "run.mat", squeeze_me=True, struct_as_record=False)
    cycle, diag, frames, meta = mat["cycle"], mat["diagnostics"], mat["can"], mat["meta"]
    for i, rec in enumerate(raw_messages(log_path, "/controller/cycle")):
        for field, value in rec.items():
            names = columns_of(field, value) if isinstance(value, list) else [field]
            values = value if isinstance(value, list) else [value]
            for name, v in zip(names, values, strict=True):
                got = scalar(getattr(cycle, name)[i])
                assert same(got, v), (rec["tick"], name, got, v)
    assert list(diag.controller_deadline_misses) == [0, 0, 2, 2, 2]
    assert list(frames.message[:2]) == ["Sync", "JointPosition"]
    assert json.loads(meta.config_json)["controller"]["law"] == "ioc"
    assert meta.clock == "lockstep"
    records = loadmat(tmp_path / "run.mat")  # structs as records: their fields name the dtype
    names = [n for k in ("cycle", "diagnostics", "can", "meta") for n in records[k].dtype.names]
    assert "controller_deadline_misses" in names and "config_json" in names
    assert all(n.isidentifier() and n[0].isalpha() and len(n) <= 63 for n in names)


@pytest.mark.parametrize(
    ("out", "extra", "words"),
    [
        ("afile/sub", (), "afile is not a directory"),
        ("all.csv", (), "holds one topic"),
    ],
)
def test_export_refuses_an_unusable_output_before_any_work(tmp_path, capsys, out, extra, words):
    (tmp_path / "afile").write_text("x")
    missing_log = tmp_path / "no-such.mcap"  # never opened: the output is checked first
    argv = ["export", str(missing_log), "--format", "csv", "--out", str(tmp_path / out), *extra]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and "\n" not in err and "no-such" not in err


# -------------------------------------------------------------------------------- info


def test_info_on_a_clean_log(log_path, capsys):
    assert main(["info", str(log_path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    cfg_json = RigConfig().with_overrides({"controller.law": "ioc"}).to_json()
    assert info["config_digest"] == "sha256:" + hashlib.sha256(cfg_json.encode()).hexdigest()
    assert info["ticks"] == TICKS and (info["first_tick"], info["last_tick"]) == (0, TICKS - 1)
    assert info["laws"] == {"hold": 1, "ioc": TICKS - 1}
    assert info["deadline_misses"] == 2 and info["missed_periods"] == 2
    assert info["duration_s"] == pytest.approx(TICKS * PERIOD_NS / 1e9)
    assert info["problems"] == [] and not info["truncated"] and info["notes"] == []
    assert info["run"]["clock"] == "lockstep" and info["run"]["recorder"] == "thread"
    assert info["run"]["can"] == "virtual" and info["run"]["zenoh"] == "tcp/127.0.0.1:1"
    assert {t: v["messages"] for t, v in info["topics"].items()} == raw_counts(log_path)
    assert info["topics"]["/controller/cycle"]["schema"] == "hil.ControllerCycle"
    assert main(["info", str(log_path)]) == 0
    text = capsys.readouterr().out
    assert "problems:        none" in text and "/hal/can/rx" in text and "complete" in text


def test_info_problems_use_the_run_rule(tmp_path, capsys):
    from rt_controller.runtime.counters import run_problems

    path = record(tmp_path / "bad.mcap", 30, watchdog_trips=2, disarmed=3)
    assert main(["info", str(path), "--json"]) == 0
    problems = json.loads(capsys.readouterr().out)["problems"]
    assert problems == ["2 DSP watchdog trip(s)", "3 tick(s) without an enabled DSP (disarmed 3)"]
    assert problems == run_problems({"watchdog_trips": 2, "drive_ticks": {"disarmed": 3}})


def test_info_on_a_truncated_log(tmp_path, capsys):
    whole = record(tmp_path / "whole.mcap", 400, chunk=2048)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])  # a SIGKILLed writer
    assert main(["info", str(cut), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["truncated"] and 0 < info["ticks"] < 400
    assert info["config_digest"] is not None and info["laws"]["hold"] == 1
    # records still queued at the last diagnostics are not lost ones
    assert info["problems"] == [
        "the MCAP log is incomplete: the writer did not finish it (truncated)"
    ]
    assert any("footer" in n or "damaged" in n for n in info["notes"])
    run = load(cut)
    assert run.truncated and len(run.cycles) == info["ticks"]
    assert main(["info", str(cut)]) == 0
    assert "TRUNCATED" in capsys.readouterr().out


def test_info_a_killed_controllers_log_is_not_clean(tmp_path, capsys):
    path = record(tmp_path / "killed.mcap", 60, final=False)
    assert main(["info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert not info["truncated"] and info["recovered"] is None
    assert info["problems"] == [
        "no final /diagnostics record: the run did not end in order (the controller or its "
        "recorder was killed, or the log was cut) after 60 ticks"
    ]


def test_info_on_a_recovered_log_says_where_it_came_from(tmp_path, capsys):
    whole = record(tmp_path / "whole.mcap", 400, chunk=2048)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    assert main(["recover", str(cut), "--out", str(tmp_path / "rec.mcap")]) == 0
    capsys.readouterr()
    assert main(["info", str(tmp_path / "rec.mcap"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    rec = info["recovered"]
    assert rec["from"] == str(cut) and rec["input_bytes"] == cut.stat().st_size
    assert 0 < rec["kept_bytes"] < rec["input_bytes"] and rec["lost_bytes"] > 0
    assert not info["truncated"] and "did not end in order" in info["problems"][0]
    assert main(["info", str(tmp_path / "rec.mcap")]) == 0
    assert f"recovered:       recovered by `hil recover` from {cut}" in capsys.readouterr().out


def test_info_on_files_hil_did_not_write(tmp_path, capsys):
    foreign = tmp_path / "other.mcap"
    with foreign.open("wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="someone-else 1.0")
        schema = w.register_schema("Point", "jsonschema", b"{}")
        channel = w.register_channel("/points", "json", schema)
        w.add_message(channel, log_time=1, publish_time=1, data=b'{"x": 1}')
        w.finish()
    text = tmp_path / "notes.txt"
    text.write_text("not a log\n")
    for path, words in ((foreign, "not a hil log"), (text, "not an MCAP file")):
        assert main(["info", str(path)]) == 2
        captured = capsys.readouterr()
        err = captured.err.strip()
        assert words in err and "\n" not in err and captured.out == ""
        assert "Traceback" not in err
    with pytest.raises(LogError, match="/points"):
        load(foreign)
