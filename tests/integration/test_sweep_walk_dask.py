"""``hil sweep`` on a local Dask cluster, off its path: a results folder of one engine given
to the other, and a sweep while another holds the scheduler's default HTTP port. Each sweep
is one short run (1 simulated second) in a ``hil sweep`` process of its own."""

from __future__ import annotations

import contextlib
import json
import socket
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration

ONE = """
[study]
duration_s = 1.0
[base.controller]
law = "ioc"
[base.camera]
model = "analytic"
"""


def sweep(spec: Path, out: Path, *extra: str) -> subprocess.CompletedProcess:
    argv = [sys.executable, "-m", "rt_controller.cli", "sweep", str(spec), "--out", str(out),
            "--workers", "1", "--no-progress", "--json", *extra]  # fmt: skip
    return subprocess.run(argv, capture_output=True, text=True, timeout=300)


def journal_engines(out: Path) -> list[str]:
    lines = (out / "rows.jsonl").read_text().splitlines()
    return [json.loads(line)["engine"] for line in lines if line.strip()]


def test_a_folder_of_the_simulate_engine_refuses_the_rig_engines_runs(tmp_path: Path):
    """The spec hash leaves the engine out (both engines run the same seeds), so before this
    the rig's row joined the simulate one and the report said '2 of 1 finished'."""
    spec = tmp_path / "one.toml"
    spec.write_text(ONE)
    out = tmp_path / "out"
    first = sweep(spec, out)
    assert first.returncode == 0, first.stderr[-2000:]
    second = sweep(spec, out, "--engine", "rig")
    assert second.returncode == 2, second.stderr[-2000:]
    err = second.stderr.strip()
    assert "\n" not in err and "holds this study's runs on the simulate engine" in err
    assert journal_engines(out) == ["simulate"]
    assert "1 of 1 finished" in (out / "report.md").read_text()


def test_a_sweep_beside_another_clusters_dashboard_port_prints_no_warning(tmp_path: Path):
    """8787 held (here by this test, else by whoever holds it): the local cluster's HTTP server
    takes a free port quietly instead of warning 'Port 8787 is already in use'."""
    spec = tmp_path / "one.toml"
    spec.write_text(ONE)
    with contextlib.ExitStack() as stack:
        holder = stack.enter_context(socket.socket())
        with contextlib.suppress(OSError):  # taken already: just as good for this test
            holder.bind(("127.0.0.1", 8787))
            holder.listen()
        proc = sweep(spec, tmp_path / "out")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "8787" not in proc.stderr and "Warning" not in proc.stderr, proc.stderr[-2000:]
