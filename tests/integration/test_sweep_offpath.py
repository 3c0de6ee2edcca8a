"""``hil sweep`` off its path: a ``--scheduler`` that accepts connections and never speaks
Dask (and Ctrl-C while waiting for it), a scheduler that goes away mid-sweep, and a results
folder on a disk that fills up. Each sweep is a ``hil sweep`` process of its own, on loopback
only."""

from __future__ import annotations

import json
import logging
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration

ONE = """
[study]
duration_s = 0.5
[base.controller]
law = "ioc"
[base.camera]
model = "analytic"
"""


def sweep(spec: Path, out: Path, *extra: str, timeout: float = 300) -> subprocess.CompletedProcess:
    argv = [sys.executable, "-m", "rt_controller.cli", "sweep", str(spec), "--out", str(out),
            "--no-progress", *extra]  # fmt: skip
    return subprocess.run(argv, capture_output=True, text=True, timeout=timeout)


def test_a_scheduler_address_that_never_answers_is_refused_in_one_line(tmp_path: Path):
    """A listener that accepts and stays silent (not a Dask scheduler): Dask's client waits
    for its handshake forever, whatever its timeout; before this the sweep hung."""
    spec = tmp_path / "one.toml"
    spec.write_text(ONE)
    with socket.create_server(("127.0.0.1", 0)) as server:  # accepts (backlog), never speaks
        address = f"tcp://127.0.0.1:{server.getsockname()[1]}"
        done = sweep(spec, tmp_path / "out", "--scheduler", address, timeout=120)
    err = done.stderr.strip()
    assert done.returncode == 2, err[-2000:]
    assert "\n" not in err and f"--scheduler {address}: cannot connect" in err
    assert "no Dask handshake" in err


def test_a_worker_s_address_for_the_scheduler_is_named_as_such(tmp_path: Path):
    """A Dask worker's address given as --scheduler: before this, 'Worker.identity() got an
    unexpected keyword argument' from deep in Dask."""
    from distributed import LocalCluster

    spec = tmp_path / "one.toml"
    spec.write_text(ONE)
    kw = {"processes": False, "protocol": "tcp://", "host": "127.0.0.1", "dashboard_address": None}
    with LocalCluster(n_workers=1, silence_logs=logging.ERROR, **kw) as cluster:
        (worker,) = cluster.scheduler.workers
        done = sweep(spec, tmp_path / "out", "--scheduler", worker, timeout=120)
    err = done.stderr.strip()
    assert done.returncode == 2, err[-2000:]
    assert err == (
        f"hil sweep: error: --scheduler {worker}: a Dask worker, not a scheduler "
        "(`dask scheduler` prints its address, port 8786 by default)"
    )


def test_ctrl_c_while_connecting_is_an_interrupted_sweep(tmp_path: Path):
    """SIGINT while the sweep waits for a silent ``--scheduler``: status 130 and the resume
    line, as any Ctrl-C (before this: 'cannot connect ...: interrupted by SIGINT', status 2)."""
    spec = tmp_path / "one.toml"
    spec.write_text(ONE)
    with socket.create_server(("127.0.0.1", 0)) as server:
        address = f"tcp://127.0.0.1:{server.getsockname()[1]}"
        argv = [sys.executable, "-m", "rt_controller.cli", "sweep", str(spec), "--out",
                str(tmp_path / "out"), "--no-progress", "--scheduler", address]  # fmt: skip
        run = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        server.settimeout(60)
        conn, _ = server.accept()  # the sweep is connecting now
        with conn:
            run.send_signal(signal.SIGINT)
            _, err = run.communicate(timeout=60)
    assert run.returncode == 130, err[-2000:]
    assert "interrupted after 0 run(s)" in err and "cannot connect" not in err, err


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def journal_rows(out: Path) -> list[dict]:
    path = out / "rows.jsonl"
    lines = path.read_text().splitlines() if path.exists() else []
    return [json.loads(line) for line in lines if line.strip()]


def test_a_scheduler_that_goes_away_records_no_run_it_never_ran(tmp_path: Path):
    """The scheduler of ``--scheduler`` killed after the first row: the runs it never ran are
    not rows (before this each became a 'failed' run, so the report said all had finished and
    a resume skipped them); one line says what happened and that the same command resumes."""
    spec = tmp_path / "ten.toml"
    spec.write_text(ONE.replace("duration_s = 0.5", "duration_s = 200.0\nrepetitions = 10"))
    out, address = tmp_path / "out", f"tcp://127.0.0.1:{free_port()}"
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    dask = [sys.executable, "-m", "distributed.cli"]
    scheduler = subprocess.Popen([*dask[:2], "distributed.cli.dask_scheduler", "--host",
        "127.0.0.1", "--port", address.rsplit(":")[-1], "--no-dashboard"], **quiet)  # fmt: skip
    worker = subprocess.Popen([*dask[:2], "distributed.cli.dask_worker", address,
        "--nthreads", "1", "--no-dashboard"], **quiet)  # fmt: skip
    try:
        argv = [sys.executable, "-m", "rt_controller.cli", "sweep", str(spec), "--out", str(out),
                "--no-progress", "--scheduler", address]  # fmt: skip
        run = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        while not journal_rows(out) and run.poll() is None:
            time.sleep(0.1)
        scheduler.kill()
        _, err = run.communicate(timeout=120)
    finally:
        for proc in (scheduler, worker):
            proc.kill()
            proc.wait(timeout=30)
    rows = journal_rows(out)
    assert 1 <= len(rows) < 10 and {r["status"] for r in rows} == {"ok"}, rows
    err = err.strip()
    assert run.returncode == 1, err[-2000:]
    assert "\n" not in err and f"the Dask cluster at {address} went away" in err, err
    assert "the same command resumes" in err


@pytest.fixture
def tiny_disk(tmp_path: Path):
    """A 200 KiB tmpfs (needs root; skips where it cannot be mounted), unmounted after."""
    mnt = tmp_path / "tiny"
    mnt.mkdir()
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=200k", "tmpfs", str(mnt)],
                          capture_output=True, text=True)  # fmt: skip
    if made.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs: {made.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], check=True)


def fill(disk: Path, leave_pages: int) -> Path:
    """A file that leaves ``leave_pages`` free pages on ``disk``."""
    import os

    st = os.statvfs(disk)
    filler = disk / "filler"
    filler.write_bytes(b"\0" * (st.f_bavail - leave_pages) * st.f_frsize)
    return filler


@pytest.mark.parametrize(
    ("leave_pages", "failing"),
    [(0, "sweep.json"), (1, "compile_target.json"), (2, "rows.jsonl"), (4, "results.parquet")],
)
def test_a_disk_that_fills_up_names_the_file_and_the_same_command_resumes(
    tiny_disk: Path, leave_pages: int, failing: str
):
    """Room for the folder's first files only: the write that fails is named, no temporary or
    empty file is left, and with room again the same command finishes every run once, quietly
    (before this: 'No space left on device' naming nothing, and an empty compile_target.json
    that every later run called unreadable)."""
    spec = tiny_disk.parent / "four.toml"
    spec.write_text(ONE.replace("duration_s = 0.5", "duration_s = 0.5\nrepetitions = 4"))
    out = tiny_disk / "out"
    filler = fill(tiny_disk, leave_pages)
    full = sweep(spec, out, "--workers", "1")
    err = full.stderr.strip()
    assert full.returncode == 1, err[-2000:]
    assert "\n" not in err and f"{out / failing}: " in err and "No space left on device" in err
    assert not list(out.glob(".*.tmp")) and not list(out.glob(".*.partial"))
    filler.unlink()
    again = sweep(spec, out, "--workers", "1", "--json")
    assert again.returncode == 0 and "unreadable" not in again.stderr, again.stderr[-2000:]
    assert "4 of 4 finished" in (out / "report.md").read_text()


@pytest.mark.parametrize(
    ("address", "said"),
    [
        (
            "tcp://127.0.0.1:{closed}",
            "connection refused: nothing listens on 127.0.0.1:{closed} "
            "(start one: dask scheduler --port {closed})",
        ),
        ("127.0.0.1:99999", "port 99999 is out of range (1..65535)"),
        ("tls://127.0.0.1:{closed}", "only tcp:// schedulers are supported, not tls://"),
    ],
    ids=["refused", "port-out-of-range", "tls"],
)
def test_a_scheduler_address_that_cannot_work_is_refused_at_once(
    tmp_path: Path, address: str, said: str
):
    """Before this, a refused or out-of-range address waited Dask's 20 s connect timeout and
    then said "Timed out trying to connect"; tls:// gave Dask's "TLS expects a ssl_context"."""
    with socket.create_server(("127.0.0.1", 0)) as probe:
        closed = probe.getsockname()[1]  # free once closed: nothing listens there
    spec = tmp_path / "one.toml"
    spec.write_text(ONE)
    address, said = address.format(closed=closed), said.format(closed=closed)
    done = sweep(spec, tmp_path / "out", "--scheduler", address, timeout=120)
    assert done.returncode == 2, done.stderr[-2000:]
    assert done.stderr.strip() == f"hil sweep: error: --scheduler {address}: {said}"
