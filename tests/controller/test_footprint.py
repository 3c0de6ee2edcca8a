"""The footprint reader: /proc parsing on recorded text, a live read of this process, the
summary's figures, and the memory-locking helpers of ``runtime/realtime.py``."""

from __future__ import annotations

import os
import struct
from pathlib import Path

import pytest

from rt_controller.rig.footprint import (
    MIB,
    Snapshot,
    children_of,
    cpu_percent,
    parse_stat_cpu,
    parse_status,
    read_footprint,
    role_of,
    summarize,
    thread_ticks,
)
from rt_controller.runtime.realtime import lockable, present_runs

STATUS = """Name:\tpython
Umask:\t0022
State:\tS (sleeping)
Tgid:\t4242
VmPeak:\t  700000 kB
VmSize:\t  610696 kB
VmLck:\t  125000 kB
VmPin:\t       0 kB
VmHWM:\t  236212 kB
VmRSS:\t  236212 kB
RssAnon:\t   77888 kB
RssFile:\t  158324 kB
RssShmem:\t       0 kB
Threads:\t12
SigQ:\t0/95000
voluntary_ctxt_switches:\t150
"""

# The command name may hold spaces and parentheses: fields count from the last ")".
STAT = (
    "4242 (py (thon) x) S 1 4242 4242 0 -1 4194560 30000 0 0 0 "
    "1234 567 0 0 -2 0 12 0 100 610696000 59053 18446744073709551615"
)


def test_parse_status_reads_sizes_in_bytes_and_threads() -> None:
    st = parse_status(STATUS)
    assert st["VmRSS"] == 236212 * 1024
    assert st["VmLck"] == 125000 * 1024
    assert st["RssAnon"] == 77888 * 1024
    assert st["Threads"] == 12
    assert "Umask" not in st and "voluntary_ctxt_switches" not in st


def test_parse_stat_cpu_counts_fields_after_the_command_name() -> None:
    assert parse_stat_cpu(STAT) == 1234 + 567


def _fake_proc(tmp_path: Path) -> Path:
    base = tmp_path / "4242"
    (base / "task" / "4242").mkdir(parents=True)
    (base / "task" / "4250").mkdir(parents=True)
    (base / "status").write_text(STATUS)
    (base / "stat").write_text(STAT)
    (base / "task" / "4242" / "stat").write_text(STAT)
    (base / "task" / "4242" / "comm").write_text("python\n")
    (base / "task" / "4242" / "children").write_text("5001 5002 ")
    (base / "task" / "4250" / "stat").write_text(STAT.replace("1234 567", "10 20"))
    (base / "task" / "4250" / "comm").write_text("rx-0\n")
    (base / "task" / "4250" / "children").write_text("5003")
    return tmp_path


def test_read_footprint_from_a_recorded_proc_tree(tmp_path: Path) -> None:
    proc = _fake_proc(tmp_path)
    snap = read_footprint(4242, proc)
    assert snap is not None
    assert snap.rss == 236212 * 1024 and snap.locked == 125000 * 1024
    assert snap.rss_anon + snap.rss_file == snap.rss
    assert snap.threads == 12 and snap.cpu_ticks == 1801
    assert snap.thread_ticks == {"main": 1801, "rx-0": 30}
    assert thread_ticks(4242, proc) == snap.thread_ticks
    assert sorted(children_of(4242, proc)) == [5001, 5002, 5003]


def test_a_gone_process_or_a_zombie_reads_as_none(tmp_path: Path) -> None:
    assert read_footprint(999_999, tmp_path) is None
    base = tmp_path / "7"
    base.mkdir()
    (base / "status").write_text("Name:\tx\nState:\tZ (zombie)\nThreads:\t1\n")
    (base / "stat").write_text("7 (x) Z 1 7 7 0 -1 0 0 0 0 0 5 5 0 0 20 0 1 0 0 0 0 0")
    assert read_footprint(7, tmp_path) is None


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs Linux /proc")
def test_read_footprint_of_this_process() -> None:
    snap = read_footprint(os.getpid())
    assert snap is not None
    assert snap.rss > 0 and snap.threads >= 1 and snap.cpu_ticks >= 0
    assert snap.hwm >= snap.rss and "main" in snap.thread_ticks


def test_role_of_a_rig_command_line() -> None:
    assert role_of(["python", "-m", "rt_controller.cli", "controller", "--json"]) == "controller"
    assert role_of(["/usr/bin/python3", "-m", "rt_controller.cli", "vision"]) == "vision"
    assert role_of(["python", "-m", "rt_controller.cli", "bench", "loop"]) is None
    assert role_of(["python", "-m", "pytest"]) is None


def _snap(t: float, rss_mb: int, ticks: int, threads: dict[str, int]) -> Snapshot:
    return Snapshot(
        t=t,
        rss=rss_mb * MIB,
        rss_anon=rss_mb * MIB // 2,
        rss_file=rss_mb * MIB // 2,
        locked=10 * MIB,
        hwm=rss_mb * MIB,
        threads=len(threads),
        cpu_ticks=ticks,
        thread_ticks=threads,
    )


def test_summarize_peaks_over_the_run_cpu_over_the_window() -> None:
    series = [
        _snap(0.0, 50, 0, {"main": 0}),
        _snap(1.0, 120, 300, {"main": 300}),  # start-up compile: outside the window
        _snap(2.0, 100, 310, {"main": 305, "rx-0": 5}),
        _snap(4.0, 90, 330, {"main": 315, "rx-0": 15}),
    ]
    out = summarize(series, (1.5, 4.0), hz=100.0)
    assert out["peak_rss_mb"] == 120 and out["peak_locked_mb"] == 10
    assert out["peak_threads"] == 2 and out["samples"] == 4
    assert out["cpu_window_s"] == pytest.approx(2.0)
    assert out["cpu_percent"] == pytest.approx(10.0)  # 20 ticks at 100 Hz in 2 s
    assert out["thread_cpu_percent"] == pytest.approx({"main": 5.0, "rx-0": 5.0})
    assert cpu_percent(series[0], series[1], 100.0) == pytest.approx(300.0)
    # A window without two samples has no CPU figure (never a made-up one).
    assert summarize(series, (10.0, 11.0), hz=100.0)["cpu_percent"] is None


def test_lockable_leaves_out_guard_pages_kernel_pages_and_the_llvm_compiler() -> None:
    assert lockable("rw-p", "")
    assert lockable("r-xp", "/usr/lib/libc.so.6")
    assert not lockable("---p", "")
    assert not lockable("r-xp", "[vdso]")
    assert not lockable("r-xp", "/venv/site-packages/llvmlite/binding/libllvmlite.so")


def test_present_runs_merge_contiguous_present_pages() -> None:
    present, absent = 1 << 63, 0
    entries = [present, present, absent, present, absent, absent, present]
    raw = struct.pack(f"<{len(entries)}Q", *entries)
    assert present_runs(raw, 0x1000, 0x1000) == [
        (0x1000, 0x2000),
        (0x4000, 0x1000),
        (0x7000, 0x1000),
    ]
    assert present_runs(b"", 0, 4096) == []


def test_a_child_sampled_before_its_exec_is_sampled_after_it() -> None:
    """A rig child read between its fork and its exec (the parent's command line, no role)
    is looked at again: its figures are not lost for the whole run."""
    import subprocess
    import sys
    import time

    from rt_controller.rig.footprint import FootprintSampler

    exec_on_a_line = (
        "import os, sys; sys.stdin.readline(); os.execv(sys.executable, [sys.executable, '-c', "
        "'import time; time.sleep(60)', 'rt_controller.cli', 'vision'])"
    )
    child = subprocess.Popen([sys.executable, "-c", exec_on_a_line], stdin=subprocess.PIPE)
    try:
        sampler = FootprintSampler()
        sampler.sample()  # before the exec: no role yet
        assert "vision" not in sampler.series
        child.stdin.write(b"go\n")
        child.stdin.flush()
        for _ in range(500):  # until the exec'd command line shows (no wall-clock bound)
            if role_of(Path(f"/proc/{child.pid}/cmdline").read_bytes().decode().split("\0")):
                break
            time.sleep(0.01)
        sampler.sample()
        assert "vision" in sampler.series, sampler.series
    finally:
        child.kill()
        child.wait()
