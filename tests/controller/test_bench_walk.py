"""``hil bench`` off its path: settings that would measure nothing, failed runs, Ctrl-C."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import pytest

from rt_controller.cli import main
from tests.support.proc import WAIT_S, processes_mentioning, wait_for


def test_bench_host_refuses_a_duration_shorter_than_one_period(capsys):
    """No release falls in the run: the report would be NaN figures of zero wake-ups."""
    assert main(["bench", "host", "--duration", "0.01", "--period-us", "1000000"]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    (line,) = err.strip().splitlines()
    assert "shorter than one --period-us" in line


def test_bench_solver_refuses_a_single_update(capsys):
    """The first update initialises the solver: with one there is no timed update at all."""
    with pytest.raises(SystemExit) as exc:
        main(["bench", "solver", "--updates", "1"])
    assert exc.value.code == 2
    assert "argument --updates" in capsys.readouterr().err


def test_bench_sweep_with_failed_runs_prints_its_figures_and_exits_1():
    """Runs shorter than a control period all fail: their runs/s are no engine's speed.
    In a process of its own: the Dask cluster's helper processes outlive a call."""
    pytest.importorskip("distributed")
    argv = ["bench", "sweep", "--runs", "1", "--duration", "0.001", "--rig-runs", "0"]
    cmd = [sys.executable, "-m", "rt_controller.cli", *argv, "--workers", "1", "-q"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=WAIT_S, check=False)
    assert done.returncode == 1
    assert json.loads(done.stdout)["engines"][0]["failed"] == 2  # serial and on the worker
    (line,) = done.stderr.strip().splitlines()
    assert line.startswith("hil bench sweep: 2 simulate runs failed: ")


@pytest.mark.parametrize(("sig", "status"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_ctrl_c_mid_bench_says_so_in_one_line_and_leaves_no_probe(sig, status):
    duration = f"587.{sig:d}"  # names this test's probes among the host's processes
    cmd = [sys.executable, "-m", "rt_controller.cli", "bench", "host", "--duration", duration]
    env = {**os.environ, "HIL_PROGRESS_AFTER_S": "0"}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stderr is not None
        assert "measuring" in proc.stderr.readline()  # the bench has started
        cpus = len(os.sched_getaffinity(0))  # one probe per CPU: all started, then the signal
        wait_for(lambda: len(probes(duration)) >= cpus, "the probes", proc)
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=WAIT_S)
        assert proc.returncode == status and out == ""
        said = f"hil bench host: interrupted by {sig.name}; no figures"
        assert err.strip().splitlines() == [said]
        wait_for(lambda: not probes(duration), "the probes to end")
    finally:  # a probe left behind must not run on at priority 99 for ten minutes
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for line in probes(duration):
            os.kill(int(line.split(":")[0]), signal.SIGKILL)


def probes(duration: str) -> list[str]:
    """The live probe processes of a ``hil bench host --duration DURATION``."""
    return [p for p in processes_mentioning(duration) if "rig.bench_host" in p]


@pytest.mark.integration
def test_bench_loop_without_keep_names_no_log_and_reports_can_cost_in_both_profiles():
    """Without ``--keep`` the runs' temporary folder is gone when the figures are printed: no
    ``log`` path to nothing. ``can_frame_us`` is in the cia402 comparison as in the dsp one."""
    from rt_controller.rig.bench_loop import bench_loop

    out = bench_loop(
        rates=(50.0,),
        duration=0.5,
        law="ioc",
        lockstep_duration=0,
        host_probe_s=0,
        profile="cia402",
    )
    assert [r["log"] for r in out["rates"] + out["dsp_rates"]] == [None, None]
    assert set(out["can_frame_us"]) >= {"secoc_sign_us", "encode_torque_us"}


def test_bench_tuning_whose_rig_failed_says_so_in_one_line(monkeypatch, capsys, tmp_path):
    from rt_controller.rig import bench_tuning as bt

    def failed_rig(workdir, *, requests):
        return {"requests": requests, "rig_exit": 3, "log": str(workdir / "tuning.mcap")}

    monkeypatch.setattr(bt, "bench_tuning", failed_rig)
    assert main(["bench", "tuning", "--requests", "1", "--workdir", str(tmp_path), "-q"]) == 1
    out, err = capsys.readouterr()
    assert json.loads(out)["rig_exit"] == 3
    (line,) = err.strip().splitlines()
    assert line.startswith("hil bench tuning: the rig exited with status 3")


def test_bench_tuning_whose_rig_failed_gives_its_stderr_tail(monkeypatch, capsys, tmp_path):
    """The rig's last stderr lines follow the error line (the reason, as ``hil up`` gives it);
    without ``--workdir`` no log is named (it was in a removed temporary folder)."""
    from rt_controller.rig import bench_tuning as bt

    def failed_rig(workdir, *, requests):
        tail = "hil controller: fault: no CAN\nhil up: controller exited with status 1"
        return {"requests": requests, "rig_exit": 1, "log": None, "stderr_tail": tail}

    monkeypatch.setattr(bt, "bench_tuning", failed_rig)
    monkeypatch.chdir(tmp_path)
    assert main(["bench", "tuning", "--requests", "1", "-q"]) == 1
    assert capsys.readouterr().err.splitlines() == [
        "hil bench tuning: the rig exited with status 1:",
        "hil controller: fault: no CAN",
        "hil up: controller exited with status 1",
    ]
    assert list(tmp_path.iterdir()) == []  # nothing made in the working directory


def test_bench_vision_whose_realtime_rig_was_not_clean_exits_1(monkeypatch, capsys):
    """As ``hil bench loop`` and ``soak``: the figures printed, the status and one line tell."""
    from rt_controller.rig import bench_vision as bv

    def unclean(cfg, render, truth, **kw):
        realtime = {"problems": ["1 DSP watchdog trip(s)"], "exit_codes": {"controller": 0}}
        return {"poses": 4, "realtime": realtime}

    monkeypatch.setattr(bv, "bench_vision", unclean)
    assert main(["bench", "vision", "--latency-frames", "0", "--lockstep-duration", "0"]) == 1
    out, err = capsys.readouterr()
    assert json.loads(out)["poses"] == 4
    (line,) = err.strip().splitlines()
    assert line == "hil bench vision: realtime run not clean: 1 DSP watchdog trip(s)"


def test_bench_soak_refuses_a_sample_period_that_leaves_no_rss_growth(capsys):
    """With one sample every 100 s in a 4 s run the soak's main figures would be empty."""
    argv = ["bench", "soak", "--duration", "4", "--sample", "100", "--warmup", "1", "-q"]
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert out == ""
    (line,) = err.strip().splitlines()
    assert "fewer than two RSS samples after the --warmup" in line


@pytest.mark.integration
def test_a_bench_loop_stopped_by_sigterm_leaves_no_temporary_folder(tmp_path):
    """Its runs' MCAP logs and the rig's key are in temporary folders: gone with the bench."""
    cmd = [sys.executable, "-m", "rt_controller.cli", "bench", "loop", "--rates", "50"]
    cmd += ["--duration", "60", "--host-probe", "0", "--lockstep-duration", "0"]
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        wait_for(lambda: any(tmp_path.glob("hil-bench-*/loop-50.mcap")), "the run's log", proc)
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=WAIT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 143 and out == ""
    assert err.strip().splitlines()[-1] == "hil bench loop: interrupted by SIGTERM; no figures"
    wait_for(lambda: not list(tmp_path.glob("hil-*")), "the temporary folders to go")


@pytest.mark.integration
def reap_bench(proc: subprocess.Popen, rig: str) -> None:
    """The bench ``proc`` and every process mentioning ``rig`` gone, whatever the test saw."""
    if proc.poll() is None:
        proc.kill()
        proc.wait()
    for line in processes_mentioning(rig):
        os.kill(int(line.split(":")[0]), signal.SIGKILL)


def test_a_bench_tuning_interrupted_mid_run_leaves_no_rig_process_running(tmp_path):
    """Ctrl-C while its rig runs: the bench stops ``hil up`` as Ctrl-C would (its processes,
    controller first) before it says so, rather than killing it and leaving the controller and
    its recorder running on, writing into the bench's removed folder."""
    cmd = [sys.executable, "-m", "rt_controller.cli", "bench", "tuning", "--requests", "500"]
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    rig = str(tmp_path / "hil-bench-tuning-")
    try:
        wait_for(lambda: any(" controller " in p for p in processes_mentioning(rig)), "it", proc)
        wait_for(lambda: any(tmp_path.glob("hil-bench-tuning-*/tuning.mcap")), "its log", proc)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=WAIT_S)
        left = processes_mentioning(rig)  # at once: nothing may outlive the bench
    finally:
        reap_bench(proc, rig)
    assert proc.returncode == 130 and out == ""
    assert err.strip().splitlines()[-1] == "hil bench tuning: interrupted by SIGINT; no figures"
    assert left == []
    wait_for(lambda: not list(tmp_path.glob("hil-*")), "the temporary folders to go")


@pytest.mark.parametrize("rates", ["50,50", "50,200,5e1"])
def test_bench_loop_refuses_a_rate_given_twice(rates, capsys):
    """One log per rate (``--keep DIR``: loop-50.mcap): a second run at 50 Hz would replace the
    first's while the figures of both named the same file."""
    with pytest.raises(SystemExit) as exc:
        main(["bench", "loop", "--rates", rates, "--config", "/nonexistent/rig.toml"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "argument --rates: 50 Hz given twice" in err


@pytest.mark.integration
def test_bench_loop_whose_monitor_could_not_serve_its_port_says_the_run_was_not_clean():
    """``--monitor-port`` in use: the monitor fails at start, the run goes on without it; its
    figures must not pass for ones taken with the live view (exit 1, the reason named)."""
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = str(busy.getsockname()[1])
        cmd = [sys.executable, "-m", "rt_controller.cli", "bench", "loop", "--rates", "50"]
        cmd += ["--duration", "1", "--host-probe", "0", "--lockstep-duration", "0", "-q"]
        done = subprocess.run(
            [*cmd, "--monitor-port", port], capture_output=True, text=True, timeout=WAIT_S
        )
    assert done.returncode == 1, done.stderr
    (run,) = json.loads(done.stdout)["rates"]
    assert any("hil monitor failed" in p and port in p for p in run["problems"])
    assert "hil bench loop: dsp run not clean at 50 Hz: hil monitor failed" in done.stderr


@pytest.mark.parametrize(
    ("what", "seconds"),
    [
        (["loop", "--rates", "50", "--duration", "0.01", "--host-probe", "0"], "0.03"),
        (["vision", "--grid", "2", "--latency-frames", "0", "--realtime-duration", "0"], "0.01"),
    ],
)
def test_a_lockstep_run_shorter_than_two_periods_is_refused_before_any_run(what, seconds):
    """One cycle gives a NaN speed (``NaN`` is no JSON), none a KeyError traceback."""
    cmd = [sys.executable, "-m", "rt_controller.cli", "bench", *what, "-q"]
    done = subprocess.run(
        [*cmd, "--lockstep-duration", seconds], capture_output=True, text=True, timeout=WAIT_S
    )
    assert done.returncode == 2 and done.stdout == ""
    (line,) = done.stderr.strip().splitlines()
    assert line == (
        f"hil bench {what[0]}: error: --lockstep-duration {seconds} s is shorter than two control "
        "periods at 50 Hz (0.04 s): the lockstep run would time nothing (0 skips it)"
    )


@pytest.mark.integration
def test_a_bench_tuning_whose_controller_dies_mid_run_names_the_rig_not_the_link(tmp_path):
    """The client's next request fails at once while ``hil up`` is still stopping the rest:
    the error is the rig's end and reason, not "no controller on this endpoint yet"."""
    from tests.support import cycles_logged

    cmd = [sys.executable, "-m", "rt_controller.cli", "bench", "tuning", "--requests", "500"]
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    rig = str(tmp_path / "hil-bench-tuning-")
    try:
        wait_for(lambda: any(tmp_path.glob("hil-bench-tuning-*/tuning.mcap")), "its log", proc)
        (log,) = tmp_path.glob("hil-bench-tuning-*/tuning.mcap")
        wait_for(lambda: cycles_logged(log) >= 200, "the measurement", proc, poll_s=0.5)
        (ctl,) = [p for p in processes_mentioning(rig) if " controller " in p]
        os.kill(int(ctl.split(":")[0]), signal.SIGKILL)
        out, err = proc.communicate(timeout=WAIT_S)
    finally:
        reap_bench(proc, rig)
    assert proc.returncode == 2 and out == ""
    assert "hil bench tuning: error: rig (hil up) exited with status" in err
    assert "controller killed by SIGKILL" in err and "no answer" not in err
