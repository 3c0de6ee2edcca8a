"""A sweep's rows without Dask: the engine in-process, the store's dedupe and resume."""

from __future__ import annotations

import json
from pathlib import Path

import pyarrow.parquet as pq

from plant_emulator.world import World
from rt_controller.errors import ControllerConfigError
from rt_controller.sweep.engines import Engine, run_task
from rt_controller.sweep.report import write_report
from rt_controller.sweep.results import JOURNAL, PARQUET, ResultStore
from rt_controller.sweep.spec import spec_from_dict

SPEC = {
    "study": {"duration_s": 0.5, "repetitions": 2},
    "base": {"camera": {"noise_px": 0.5}},
    "axes": [{"key": "plant.z_wo", "values": [1.0, 1.2]}],
}


def test_a_run_is_a_pure_function_of_its_task():
    task = spec_from_dict(SPEC).tasks()[1]
    a, b = Engine(World)(task), run_task(task, World)
    assert a["status"] == "ok" and a["ticks"] == 25
    assert {k: v for k, v in a.items() if k != "wall_s"} == {
        k: v for k, v in b.items() if k != "wall_s"
    }


def test_a_failing_run_is_a_row():
    task = spec_from_dict(SPEC).tasks()[0]

    def broken(_cfg):
        raise RuntimeError("plant on fire")

    row = run_task(task, broken)
    assert row["status"] == "failed" and "RuntimeError: plant on fire" in row["error"]
    timed_out = run_task(task.__class__(**{**task.__dict__, "timeout_s": 1e-9}), World)
    assert timed_out["status"] == "failed" and "RunTimeout" in timed_out["error"]


def test_store_dedupes_by_run_key_and_survives_a_torn_journal(tmp_path: Path):
    spec = spec_from_dict(SPEC)
    tasks = spec.tasks()
    rows = [run_task(t, World) for t in tasks]
    with ResultStore(tmp_path, spec) as store:
        for row in rows[:3]:
            store.add(row)
        store.add(rows[0])  # a run delivered twice is kept once
    with (tmp_path / JOURNAL).open("a") as f:
        f.write('{"run_key": "torn')  # a sweep killed mid-write
    with ResultStore(tmp_path, spec) as store:
        assert store.done() == {t.key for t in tasks[:3]}
        store.add(rows[3])
    with ResultStore(tmp_path, spec) as store:
        assert store.done() == {t.key for t in tasks}
    table = pq.read_table(tmp_path / PARQUET).to_pylist()
    assert [r["run_key"] for r in table] == [t.key for t in tasks]
    assert table[2]["J"] == rows[2]["J"]
    report = write_report(tmp_path, spec).read_text()
    assert "4 of 4 finished" in report and (tmp_path / "plots" / "J_vs_plant.z_wo.png").exists()


def test_a_folder_holds_one_study(tmp_path: Path):
    spec = spec_from_dict(SPEC)
    with ResultStore(tmp_path, spec) as store:
        store.add(run_task(spec.tasks()[0], World))
    other = spec_from_dict({**SPEC, "study": {"duration_s": 1.0}})
    try:
        ResultStore(tmp_path, other)
    except ControllerConfigError as exc:
        assert "holds another study" in str(exc)
    else:  # pragma: no cover
        raise AssertionError("a second study was accepted")
    assert json.loads((tmp_path / "sweep.json").read_text())["runs"] == 4


def test_a_study_that_kept_no_run_leaves_its_folder_to_the_next(tmp_path: Path):
    """A sweep stopped before its first row (an unreachable --scheduler) claimed the folder;
    the corrected spec takes it, as nothing of the first would be lost."""
    with ResultStore(tmp_path, spec_from_dict(SPEC)):
        pass  # no run kept
    other = spec_from_dict({**SPEC, "study": {"duration_s": 1.0}})
    with ResultStore(tmp_path, other) as store:
        assert store.done() == set()
    assert json.loads((tmp_path / "sweep.json").read_text())["spec_hash"] == other.spec_hash
