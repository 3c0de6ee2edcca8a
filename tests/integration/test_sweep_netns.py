"""``hil sweep --scheduler`` across hosts: a Dask scheduler (and the sweep's client) in one
Linux network namespace, a Dask worker in another, joined by a veth pair (192.0.2.0/24,
TEST-NET-1, inside the namespaces only), started with the ``dask scheduler`` / ``dask worker``
commands of the docs. The rows equal the serial in-process loop's, bit for bit.

Needs root and ``ip netns``; skips with one line where namespaces cannot be made.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from plant_emulator.world import World
from rt_controller.sweep.engines import run_task
from rt_controller.sweep.spec import load_spec
from tests.support.netns import ADDRS, veth_namespaces
from tests.support.proc import stop_all

pytestmark = pytest.mark.integration

SCHED_ADDR, WORKER_ADDR = ADDRS
PORT = 8786
SPEC = """
[study]
duration_s = 2.0
repetitions = 2
[base.camera]
noise_px = 0.5
[[axes]]
key = "plant.z_wo"
values = [0.9, 1.1]
"""


@pytest.fixture
def namespaces() -> Iterator[tuple[str, str]]:
    with veth_namespaces("hilsch", "hilwrk", "hs") as pair:
        yield pair


def _dask(ns: str, *args: str, log: Path) -> subprocess.Popen:
    dask = str(Path(sys.executable).with_name("dask"))
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    return subprocess.Popen(
        ["ip", "netns", "exec", ns, dask, *args],
        stdout=subprocess.DEVNULL,
        stderr=log.open("wb"),
        env=env,
    )


def test_sweep_runs_on_a_worker_in_another_namespace(namespaces, tmp_path: Path):
    sched_ns, worker_ns = namespaces
    spec = tmp_path / "spec.toml"
    spec.write_text(SPEC)
    address = f"tcp://{SCHED_ADDR}:{PORT}"
    procs: list[subprocess.Popen] = []
    try:
        procs.append(
            _dask(
                sched_ns,
                "scheduler",
                "--host",
                SCHED_ADDR,
                "--port",
                str(PORT),
                "--no-dashboard",
                log=tmp_path / "scheduler.log",
            )
        )
        procs.append(
            _dask(
                worker_ns,
                "worker",
                address,
                "--host",
                WORKER_ADDR,
                "--nthreads",
                "1",
                "--nworkers",
                "1",
                "--no-dashboard",
                log=tmp_path / "worker.log",
            )
        )
        time.sleep(1.0)
        out = tmp_path / "out"
        cmd = [
            sys.executable,
            "-m",
            "rt_controller.cli",
            "sweep",
            str(spec),
            "--out",
            str(out),
            "--scheduler",
            address,
            "--no-progress",
            "--json",
        ]
        proc = subprocess.run(
            ["ip", "netns", "exec", sched_ns, *cmd], capture_output=True, text=True, timeout=300
        )
        logs = "".join(p.read_text(errors="replace")[-1500:] for p in tmp_path.glob("*.log"))
        assert proc.returncode == 0, proc.stderr[-3000:] + logs
        outcome = json.loads(proc.stdout)
        assert outcome["workers"] == 1 and outcome["scheduler"] == address
        assert outcome["ran"] == 4 and outcome["failed"] == 0
    finally:
        stop_all(procs)
    table = pq.read_table(out / "results.parquet").to_pylist()
    tasks = load_spec(spec).tasks()
    assert [r["run_key"] for r in table] == [t.key for t in tasks]
    for task, row in zip(tasks, table, strict=True):
        assert row["J"] == run_task(task, World)["J"]
