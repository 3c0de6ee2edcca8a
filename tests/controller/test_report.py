"""``hil report``: exact numbers on a synthetic log, figures, damaged logs, the Foxglove layout."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from rt_controller.cli import main
from rt_controller.errors import LogError
from rt_controller.logtools.deadline_report import summarize
from rt_controller.logtools.reader import read_log
from rt_controller.runtime.record_encoding import CANOPEN_SCHEMA
from rt_controller.runtime.recorder import CycleRecorder, cycle_schema

N = 200
T0 = 5_000_000_000
PERIOD_NS = 20_000_000  # the default 50 Hz
MISSES = {50: (25000.0, 1), 120: (1500.0, 0), 199: (30000.0, 2)}  # tick: (lateness_us, skipped)
ROOT = Path(__file__).resolve().parents[2]


def crafted(i: int) -> dict:
    """Tick i of the synthetic run; every count in the report is known by construction."""
    late, skipped = MISSES.get(i, (-0.5 if i == 10 else float(i % 10), 0))
    return {
        "tick": i,
        "t_ns": T0 + i * PERIOD_NS + round(late * 1e3),
        "sim_time_s": None,
        "lateness_us": late,
        "read_us": 2.0,
        "solve_us": 40.0 + i % 5,
        "write_us": 3.0,
        "cycle_us": 21000.0 if i in MISSES else 100.0,
        "deadline_miss": i in MISSES,
        "missed_periods": skipped,
        "q": [0.1, 0.2],
        "dq": [0.0, 0.0],
        "f": [3.0 + (N - 1 - i), 4.0 + (N - 1 - i)],
        "f_age_ms": 5.0,
        "state_age_ms": 80.0 if i in (70, 71) else 1.0,
        "f_valid": i not in (62, 63),
        "f_stale": 60 <= i <= 64,
        "xi": [0.01 * i, -0.01 * i],
        "u": [1.0, -1.0],
        "tau": [2.0, -2.0],
        "tau_saturated": 80 <= i <= 83,
        "law": "rhc",
        "residual": 1e-3 * (i % 4),
        "iterations": 5,
        "fallback": i in (30, 31, 32),
        "cost": 0.5,
        "V": 1.0,
    }


@pytest.fixture
def synthetic(tmp_path, cfg) -> Path:
    path = tmp_path / "synthetic.mcap"
    with CycleRecorder(path, cfg, run_info={"law": "rhc"}, chunk_size=4096) as rec:
        for i in range(N):
            assert rec.record_cycle(crafted(i))
    return path


def test_numbers_are_exact(synthetic):
    r = summarize(read_log(synthetic))
    assert r["ticks"] == N and not r["truncated"] and r["notes"] == []
    assert r["law"] == "rhc" and r["rate_hz"] == 50.0 and r["period_us"] == 20000.0
    assert r["deadline_misses"] == 3 and r["miss_pct"] == 1.5 and r["missed_periods"] == 3
    t_ns = [crafted(i)["t_ns"] for i in range(N)]
    assert r["misses"] == [
        {
            "tick": i,
            "t_s": (t_ns[i] - t_ns[0]) / 1e9,
            "lateness_us": MISSES[i][0],
            "cycle_us": 21000.0,
            "missed_periods": MISSES[i][1],
        }
        for i in sorted(MISSES)
    ]
    # Sorted lateness: -0.5, 17 x 0, 20 x 1, 20 x 2 ... 19 x 9, 1500, 25000, 30000.
    late = r["lateness_us"]
    assert (late["min"], late["median"], late["max"]) == (-0.5, 5.0, 30000.0)
    assert late["p99"] == pytest.approx(1500 + 0.01 * (25000 - 1500), abs=1e-9)
    cyc = r["cycle_us"]
    assert (cyc["min"], cyc["median"], cyc["p99"], cyc["max"]) == (100.0, 100.0, 21000.0, 21000.0)
    solve = r["solve_us"]
    assert (solve["min"], solve["median"], solve["p99"], solve["max"]) == (40.0, 42.0, 44.0, 44.0)
    hist = {(b["lo_us"], b["hi_us"]): b["count"] for b in r["lateness_histogram"]}
    assert hist[(None, 0)] == 1
    assert hist[(0, 1)] == 17 and hist[(1, 2)] == 20 and hist[(2, 5)] == 60 and hist[(5, 10)] == 99
    assert hist[(1000.0, 2000.0)] == 1 and hist[(20000.0, 50000.0)] == 2
    assert sum(hist.values()) == N and r["lateness_histogram"][-1]["hi_us"] == 50000.0
    assert r["residual"]["max"] == 3e-3 and r["residual_final"] == 3e-3
    assert r["iterations"]["median"] == 5
    assert r["fallbacks"] == 3 and r["stale_features"] == 5 and r["invalid_features"] == 2
    assert r["stale_state"] == 2 and r["tau_saturated"] == 4
    assert r["f_final"] == [3.0, 4.0] and r["f_final_norm"] == 5.0
    assert r["J"] == 2.0  # 200 ticks x 0.5 / 50 Hz


def test_miss_list_is_capped(synthetic):
    r = summarize(read_log(synthetic), max_list=2)
    assert r["deadline_misses"] == 3 and [m["tick"] for m in r["misses"]] == [50, 120]


def test_cli_json_one_object_or_a_list(synthetic, capsys):
    assert main(["report", str(synthetic), "--json"]) == 0
    one = json.loads(capsys.readouterr().out)
    assert one["deadline_misses"] == 3 and one["log"] == str(synthetic)
    assert main(["report", str(synthetic), str(synthetic), "--json"]) == 0
    two = json.loads(capsys.readouterr().out)
    assert isinstance(two, list) and len(two) == 2 and two[1]["J"] == 2.0


def test_cli_text_and_plots(synthetic, tmp_path, capsys):
    outdir = tmp_path / "figs"
    assert main(["report", str(synthetic), "--plot", str(outdir)]) == 0
    out = capsys.readouterr().out
    assert "deadline misses" in out and "3 (1.500 %)" in out and "lateness" in out
    names = {p.name for p in outdir.iterdir()}
    expected = {"lateness_hist", "cycle_time", "solve_time", "f", "xi", "u", "tau"}
    assert names == {f"synthetic_{n}.png" for n in expected}
    for p in outdir.iterdir():
        data = p.read_bytes()
        assert data.startswith(b"\x89PNG\r\n\x1a\n") and len(data) > 5000, p.name


def test_truncated_log_is_reported_not_crashed_on(synthetic, tmp_path, capsys):
    data = synthetic.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    log = read_log(cut)
    assert log.truncated and log.notes and log.config is not None
    assert 0 < log.n_cycles < N
    assert np.array_equal(log.cycles["tick"], np.arange(log.n_cycles))
    assert main(["report", str(cut)]) == 0
    assert "note:" in capsys.readouterr().out
    assert main(["report", str(cut), "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["truncated"] and r["ticks"] == log.n_cycles and r["notes"]

    # Any cut point: never an exception, and more file never means fewer ticks. A cut in
    # the closing magic (its last 8 bytes) loses no record: read whole, with a note.
    previous = 0
    for size in [*range(8, len(data), max(1, len(data) // 53)), len(data) - 8, len(data) - 1]:
        cut.write_bytes(data[:size])
        log = read_log(cut, raw=False)
        summarize(log)
        if size >= len(data) - 8:
            assert not log.truncated and any("closing magic" in n for n in log.notes)
        else:
            assert log.truncated
        assert log.n_cycles >= previous
        previous = log.n_cycles


def test_empty_log(tmp_path, cfg, capsys):
    path = tmp_path / "empty.mcap"
    CycleRecorder(path, cfg).close()
    r = summarize(read_log(path))
    assert r["ticks"] == 0 and any("no /controller/cycle" in n for n in r["notes"])
    assert main(["report", str(path), "--plot", str(tmp_path / "p")]) == 0


@pytest.mark.parametrize("content", [None, b"", b"not an mcap file at all", b"\x89MC"])
def test_missing_or_not_mcap_is_one_clear_line(tmp_path, capsys, content):
    path = tmp_path / "bad.mcap"
    if content is not None:
        path.write_bytes(content)
    assert main(["report", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err
    assert "no such file" in err if content is None else "not an MCAP file" in err
    with pytest.raises(LogError):
        read_log(path)


def test_foxglove_layout_plots_cycle_fields_and_canopen_frames():
    layout = json.loads((ROOT / "foxglove" / "layout.json").read_text(encoding="utf-8"))
    panels = layout["configById"]

    def leaves(node):
        if isinstance(node, str):
            yield node
            if node.startswith("Tab!"):
                for tab in panels[node]["tabs"]:
                    yield from leaves(tab["layout"])
        else:
            yield from leaves(node["first"])
            yield from leaves(node["second"])

    assert set(leaves(layout["layout"])) == set(panels)
    fields = set(cycle_schema()["properties"])
    frame = CANOPEN_SCHEMA["properties"]
    plotted = set()
    for pid, conf in panels.items():
        for p in conf.get("paths", []):
            # a message path: topic, filters {field==value}, then the field
            topic, filters, path = re.fullmatch(
                r"([^{.]+)((?:\{[^}]*\})*)\.(.+)", p["value"]
            ).groups()
            if topic == "/hal/canopen":  # the cia402 bus, one message per frame
                for name in re.findall(r"\{(\w+)==", filters):
                    assert name in frame, (pid, name)
                assert path.split(".")[0] == "fields", (pid, path)
                assert path.split(".")[1] in frame["fields"]["properties"], (pid, path)
                continue
            assert topic == "/controller/cycle" and not filters, pid
            name = path.split("[")[0]
            assert name in fields, (pid, name)
            plotted.add(name)
    assert {"f", "xi", "u", "tau", "lateness_us", "cycle_us", "solve_us", "residual"} <= plotted


def test_nan_cost_is_left_out_of_j(tmp_path, cfg):
    path = tmp_path / "nan.mcap"
    with CycleRecorder(path, cfg) as rec:
        for i in range(10):
            c = crafted(i)
            c["cost"] = math.nan if i == 3 else 1.0
            rec.record_cycle(c)
    assert summarize(read_log(path))["J"] == pytest.approx(9.0 / 50.0)
