"""``hil sweep`` on real Dask clusters (local, 127.0.0.1): worker count, resume, killed workers,
model mismatch, and the two engines. Each sweep is a ``hil sweep`` process of its own; runs are
short (a few simulated seconds) and the checks never look at wall-clock times."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from plant_emulator.world import World
from rt_controller.sweep.engines import run_task
from rt_controller.sweep.spec import load_spec
from tests.support.proc import alive, children_of

pytestmark = pytest.mark.integration

MISMATCH = """
[study]
name = "mismatch"
duration_s = 3.0
repetitions = 2
[base.camera]
noise_px = 0.5
[base.controller]
law = "ioc"
[[axes]]
key = "plant.z_wo"
values = [1.0, 1.2, 1.4]
[[axes]]
key = "plant.theta1"
distribution = "uniform"
low = 0.9
high = 1.1
samples = 2
"""

LONGER = """
[study]
name = "longer"
duration_s = 6.0
repetitions = 4
[base.camera]
noise_px = 0.5
[base.controller]
law = "rhc"
[[axes]]
key = "plant.s_lambda"
values = [0.9, 1.0, 1.1, 1.2, 1.3]
"""


def sweep_cmd(spec: Path, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "rt_controller.cli", "sweep", str(spec), "--out", str(out),
            "--no-progress", "--json", *extra]  # fmt: skip


def run_sweep(spec: Path, out: Path, *extra: str) -> dict:
    proc = subprocess.run(sweep_cmd(spec, out, *extra), capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout)


def rows(out: Path) -> list[dict]:
    return pq.read_table(out / "results.parquet").to_pylist()


def without_wall(table: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k != "wall_s"} for r in table]


def journal_keys(out: Path) -> list[str]:
    lines = (out / "rows.jsonl").read_text().splitlines()
    return [json.loads(line)["run_key"] for line in lines if line.strip()]


@pytest.fixture(scope="module")
def mismatch(tmp_path_factory) -> tuple[Path, Path]:
    """The mismatch study on two workers: (spec, results folder)."""
    base = tmp_path_factory.mktemp("sweep")
    spec = base / "mismatch.toml"
    spec.write_text(MISMATCH)
    out = base / "two"
    outcome = run_sweep(spec, out, "--workers", "2")
    assert outcome["ran"] == 12 and outcome["failed"] == 0 and outcome["workers"] == 2
    return spec, out


def test_one_worker_and_two_workers_give_identical_rows(mismatch, tmp_path: Path):
    spec, two = mismatch
    one = tmp_path / "one"
    assert run_sweep(spec, one, "--workers", "1")["workers"] == 1
    a, b = without_wall(rows(one)), without_wall(rows(two))
    assert len(a) == 12 and a == b  # bit for bit, in (point, repetition) order
    # and the serial in-process loop gives the same numbers
    tasks = load_spec(spec).tasks()
    for task in (tasks[0], tasks[-1]):
        serial = run_task(task, World)
        row = next(r for r in a if r["run_key"] == task.key)
        assert serial["J"] == row["J"] and serial["f_final_norm"] == row["f_final_norm"]


def test_J_rises_with_the_depth_mismatch(mismatch):
    """The plant's target plane farther than the controller's model: the real image gain is
    lower than the nominal one and the servo slower, so J grows with the mismatch."""
    _, out = mismatch
    table = rows(out)
    assert all(r["status"] == "ok" for r in table)
    by_z: dict[float, list[float]] = {}
    for r in table:
        by_z.setdefault(r["plant.z_wo"], []).append(r["J"])
    medians = [sorted(v)[len(v) // 2] for _, v in sorted(by_z.items())]
    assert medians == sorted(medians) and medians[0] < medians[-1]
    report = (out / "report.md").read_text()
    assert "J against `plant.z_wo`" in report and (out / "plots" / "J_vs_plant.z_wo.png").exists()


def _wait_rows(out: Path, n: int, proc: subprocess.Popen, timeout: float = 180) -> int:
    deadline = time.monotonic() + timeout
    journal = out / "rows.jsonl"
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()[1][-3000:]
        count = len(journal.read_text().splitlines()) if journal.exists() else 0
        if count >= n:
            return count
        time.sleep(0.02)
    raise AssertionError(f"fewer than {n} rows after {timeout} s")


def test_an_interrupted_sweep_resumes_without_duplicates_or_gaps(tmp_path: Path):
    spec = tmp_path / "longer.toml"
    spec.write_text(LONGER)
    out = tmp_path / "out"
    proc = subprocess.Popen(
        sweep_cmd(spec, out, "--workers", "1"), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    try:
        _wait_rows(out, 3, proc)
        proc.send_signal(signal.SIGINT)  # Ctrl-C
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err[-3000:]
    assert "the same command resumes" in err
    first = rows(out)
    assert 3 <= len(first) < 20 and all(r["status"] == "ok" for r in first)
    outcome = run_sweep(spec, out, "--workers", "1")
    assert outcome["skipped"] == len(first) and outcome["ran"] == 20 - len(first)
    table = rows(out)
    keys = [r["run_key"] for r in table]
    assert sorted(keys) == sorted(t.key for t in load_spec(spec).tasks())
    assert len(journal_keys(out)) == 20  # no finished run was run again
    assert without_wall(table[: len(first)]) != [] and all(r["status"] == "ok" for r in table)


def _workers_of(pid: int) -> list[int]:
    """The Dask worker processes of a ``hil sweep`` (spawned children of its nannies)."""
    out = []
    for child in children_of(pid):
        try:
            cmd = Path(f"/proc/{child}/cmdline").read_bytes()
        except OSError:
            continue
        if b"spawn_main" in cmd and alive(child):
            out.append(child)
    return out


def test_a_worker_killed_mid_sweep_loses_and_duplicates_nothing(tmp_path: Path):
    spec = tmp_path / "longer.toml"
    spec.write_text(LONGER)
    out = tmp_path / "out"
    proc = subprocess.Popen(
        sweep_cmd(spec, out, "--workers", "2"), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    try:
        done_at_kill = _wait_rows(out, 2, proc)
        workers = _workers_of(proc.pid)
        assert len(workers) == 2, workers
        os.kill(workers[0], signal.SIGKILL)
        stdout, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err[-3000:]
    assert done_at_kill < 20
    table = rows(out)
    assert sorted(r["run_key"] for r in table) == sorted(t.key for t in load_spec(spec).tasks())
    assert all(r["status"] == "ok" for r in table)
    assert len(journal_keys(out)) == 20  # every run recorded exactly once
    assert json.loads(stdout)["ran"] == 20


def test_the_same_point_gives_the_same_J_on_simulate_and_rig(tmp_path: Path):
    spec = tmp_path / "one.toml"
    spec.write_text(
        '[study]\nduration_s = 3.0\n[base.controller]\nlaw = "rhc"\n'
        '[[axes]]\nkey = "plant.z_wo"\nvalues = [1.2]\n'
    )
    run_sweep(spec, tmp_path / "sim", "--workers", "1", "--engine", "simulate")
    run_sweep(spec, tmp_path / "rig", "--workers", "1", "--engine", "rig", "--keep-logs")
    (sim,), (rig,) = rows(tmp_path / "sim"), rows(tmp_path / "rig")
    assert sim["seed"] == rig["seed"] and rig["engine"] == "rig"
    assert rig["status"] == "ok" and rig["problems"] == "", rig
    assert rig["ticks"] == sim["ticks"] == 150
    # the rig adds encoder quantisation and the DSP's velocity filter: close, not equal
    assert rig["J"] == pytest.approx(sim["J"], rel=0.02)
    assert (tmp_path / "rig" / "logs" / f"{rig['run_key']}.mcap").exists()


def test_the_rig_engine_runs_both_hardware_profiles(tmp_path: Path):
    """hardware.profile as an axis of a rig sweep: the dsp and the cia402 profile run the
    same lockstep point clean, with J within 1 % (issue 39's target for the cia402 profile)."""
    spec = tmp_path / "profiles.toml"
    spec.write_text(
        '[study]\nengine = "rig"\nduration_s = 3.0\n[base.controller]\nlaw = "rhc"\n'
        '[[axes]]\nkey = "hardware.profile"\nvalues = ["dsp", "cia402"]\n'
    )
    outcome = run_sweep(spec, tmp_path / "out", "--workers", "1")
    assert outcome["ran"] == 2 and outcome["failed"] == 0
    by = {r["hardware.profile"]: r for r in rows(tmp_path / "out")}
    for r in by.values():
        assert r["status"] == "ok" and r["problems"] == "" and r["dsp_faults"] == 0, r
        assert r["ticks"] == 150 and r["deadline_misses"] == 0
    assert by["cia402"]["J"] == pytest.approx(by["dsp"]["J"], rel=0.01)
    report = (tmp_path / "out" / "report.md").read_text()
    assert "- hardware profile: cia402, dsp" in report
