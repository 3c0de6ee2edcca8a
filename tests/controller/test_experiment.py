"""``hil experiment``: planning rules, the Table I format, failures, and real daemon sweeps."""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path

import pytest

from hal.config import load_config
from rt_controller.cli import main
from rt_controller.logtools.reader import read_log
from rt_controller.rig import experiment as ex
from rt_controller.rig import experiment_results as exr
from rt_controller.rig.failures import RigProcessError

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def settings(tmp_path: Path, which: tuple[str, ...] = ex.EXPERIMENTS, **kw) -> ex.Settings:
    return ex.Settings(experiments=which, out=tmp_path, **kw)


def live_children() -> set[int]:
    """Child processes of this test process that are still running (not zombies)."""
    pids: set[int] = set()
    for task in Path(f"/proc/{os.getpid()}/task").glob("*/children"):
        pids.update(int(p) for p in task.read_text().split())
    alive = set()
    for pid in pids:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        if state != "Z":
            alive.add(pid)
    return alive


# ------------------------------------------------------------------------- planning (fast)
def test_plan_runs_each_experiment_with_the_papers_laws_and_horizons(tmp_path):
    plan = ex.plan(settings(tmp_path, reps=2), load_config())
    assert [(s.law, s.horizon_s) for s in plan["fig3"]] == [
        ("rhc", 0.02),
        ("ioc", None),
        ("pbc", None),
    ]
    assert [s.horizon_s for s in plan["fig4"]] == [0.02, 0.1, 1.0]
    assert [(s.horizon_s, s.seed) for s in plan["table1"]] == [
        (h, rep) for h in (0.02, 0.1, 1.0) for rep in range(2)
    ]
    # The embedded config's camera renders images: no pixel noise anywhere; the table1
    # repetitions differ by the seed of its sensor's noise.
    assert {s.noise_px for specs in plan.values() for s in specs} == {0.0}
    # fig3's RHC run is fig4's T = 0.02 s run: `all` runs it once.
    assert plan["fig3"][0].name == plan["fig4"][0].name == "rhc-T0.02"
    assert plan["table1"][3].name == "rhc-T0.1-seed1"
    assert plan["table1"][3].label == "RHC T = 0.1 s, seed 1"


def test_noise_option_and_config_noise_on_the_analytic_camera(tmp_path):
    analytic = load_config().with_overrides({"camera.model": "analytic"})
    plan = ex.plan(settings(tmp_path, reps=2), analytic)
    assert {s.noise_px for s in plan["fig3"] + plan["fig4"]} == {0.0}
    assert {s.noise_px for s in plan["table1"]} == {ex.TABLE1_DEFAULT_NOISE_PX}
    assert plan["table1"][3].name == "rhc-T0.1-noise0.5-seed1"
    plan = ex.plan(settings(tmp_path, noise_px=0.2), analytic)
    assert {s.noise_px for specs in plan.values() for s in specs} == {0.2}
    noisy = analytic.with_overrides({"camera.noise_px": 0.3})
    plan = ex.plan(settings(tmp_path), noisy)
    assert {s.noise_px for specs in plan.values() for s in specs} == {0.3}


def test_pixel_noise_on_the_rendering_camera_is_refused_not_reported(tmp_path):
    """camera.noise_px is the analytic camera's; the rendering camera never applied it, yet the
    runs were named and reported with it (fig3 --noise 5 gave the noise-free J)."""
    from rt_controller.errors import ControllerConfigError

    with pytest.raises(ControllerConfigError, match=r"--noise: camera\.noise_px = 0\.2 is"):
        ex.plan(settings(tmp_path, noise_px=0.2), load_config())
    noisy = load_config().with_overrides({"camera.noise_px": 0.3})
    with pytest.raises(ControllerConfigError, match=r"the config: .*camera\.model = analytic"):
        ex.plan(settings(tmp_path), noisy)


def test_run_config_uses_the_cli_step_rule_and_reads_back(tmp_path):
    s = settings(tmp_path)
    steps = {h: ex.run_config(s, ex.RunSpec("rhc", h, 0.5, 3)).rhc.steps for h in ex.HORIZONS_S}
    assert steps == {0.02: 10, 0.1: 10, 1.0: 20}
    cfg = ex.run_config(s, ex.RunSpec("rhc", 1.0, 0.5, 3))
    assert (cfg.camera.noise_px, cfg.camera.seed, cfg.controller.clock) == (0.5, 3, "lockstep")
    path = tmp_path / "c.toml"
    path.write_text(ex.config_toml(cfg), encoding="utf-8")
    assert load_config(path) == cfg


def test_ordinals():
    assert [exr.ordinal(n) for n in (1, 2, 3, 4, 11, 12, 13, 21, 22, 101)] == [
        "1st", "2nd", "3rd", "4th", "11th", "12th", "13th", "21st", "22nd", "101st"
    ]  # fmt: skip


def test_table1_markdown_is_sorted_per_row_like_the_paper():
    rows = [
        {"horizon_s": 0.02, "J_sorted": [1.5, 2.25], "J": [2.25, 1.5], "average": 1.875},
        {"horizon_s": 1.0, "J_sorted": [3.0], "J": [3.0, None], "average": None},
    ]
    assert exr.table1_markdown(rows).splitlines() == [
        "| Horizon length | 1st | 2nd | average |",
        "|---|---:|---:|---:|",
        "| T = 0.02 s | 1.500 | 2.250 | 1.875 |",
        "| T = 1.0 s | 3.000 | — | — |",
    ]
    paper = exr.paper_table1_markdown().splitlines()
    assert paper[2] == "| T = 0.02 s | 3352 | 3357 | 3367 | 3477 | 3486 | 3408 |"
    assert paper[4] == "| T = 1.0 s | 4097 | 4158 | 4204 | 4211 | 4252 | 4184 |"


def test_settings_are_validated(tmp_path):
    from rt_controller.errors import ControllerConfigError

    for bad in ({"reps": 0}, {"duration_s": 0.0}, {"noise_px": -1.0}, {"duration_s": math.nan}):
        with pytest.raises(ControllerConfigError):
            settings(tmp_path, **bad).validate()
    # the command line refuses it before anything runs: argparse's usage error, exit status 2
    with pytest.raises(SystemExit) as exc:
        main(["experiment", "table1", "--reps", "0", "--out", str(tmp_path / "x")])
    assert exc.value.code == 2
    assert not (tmp_path / "x").exists()
    # a CAN bus no process could open: refused before any run, no output folder
    argv = ["experiment", "fig3", "--can", "bogus:x", "--duration", "0.2"]
    assert main([*argv, "--out", str(tmp_path / "y")]) == 2
    assert not (tmp_path / "y").exists()


def test_failed_runs_are_reported_and_the_exit_status_is_nonzero(tmp_path, monkeypatch, capsys):
    calls = []

    def broken(opts):
        calls.append(opts.law)
        raise RigProcessError(f"controller exited with status 3:\nboom in {opts.law}")

    monkeypatch.setattr(ex, "run_rig", broken)
    out = tmp_path / "exp"
    argv = ["experiment", "fig3", "--duration", "1", "--out", str(out), "--fresh-processes"]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert sorted(calls) == ["ioc", "pbc", "rhc"]  # two at a time on a 2-CPU machine
    assert "run pbc (PBC) failed: RigProcessError: controller exited with status 3" in err
    assert "boom in pbc" in err
    res = json.loads((out / "results.json").read_text())
    assert [f["run"] for f in res["failures"]] == ["rhc-T0.02", "ioc", "pbc"]
    assert res["fig3"]["J"] == {"rhc": None, "ioc": None, "pbc": None}
    report = (out / "report.md").read_text()
    assert "## Failures" in report and "| inverse optimal (IOC) | — |" in report
    # each run again, with its planned duration (a run without ticks has no other)
    assert all(" --duration 1 " in r["command"] for r in res["runs"]), res["runs"]


def test_quiet_says_only_what_failed(tmp_path, monkeypatch, capsys):
    """``--quiet``: no plan line, progress bar or per-run line on stderr; a failed run is still
    said, with its error, after the runs."""

    def broken(opts):
        raise RigProcessError(f"controller exited with status 3:\nboom in {opts.law}")

    monkeypatch.setattr(ex, "run_rig", broken)
    argv = ["experiment", "fig3", "--duration", "1", "--out", str(tmp_path / "exp")]
    assert main([*argv, "--fresh-processes", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "runs (" not in err and "FAILED" not in err and "writing" not in err, err
    assert "hil experiment: run pbc (PBC) failed: RigProcessError" in err


def test_jobs_are_refused_where_runs_would_share_a_bus_or_the_cpu(tmp_path):
    from rt_controller.errors import ControllerConfigError

    for bad, words in (
        ({"jobs": 2, "realtime": True}, "lockstep"),
        ({"jobs": 2, "can": "socketcan:vcan0"}, "socketcan:vcan0"),
        ({"jobs": 2, "can": "udp_multicast"}, "udp_multicast"),
        ({"jobs": 0}, "at least 1"),
        ({"jobs": ex.MAX_JOBS + 1}, "at most"),
    ):
        with pytest.raises(ControllerConfigError, match=words):
            settings(tmp_path, **bad).validate()
    settings(tmp_path, jobs=2).validate()  # lockstep on the private default bus
    assert settings(tmp_path).effective_jobs() == min(os.cpu_count() or 1, ex.MAX_JOBS)
    assert settings(tmp_path, realtime=True).effective_jobs() == 1
    assert settings(tmp_path, can="socketcan:vcan0").effective_jobs() == 1
    assert settings(tmp_path, jobs=1).effective_jobs() == 1
    with pytest.raises(SystemExit) as exc:  # the command line: usage error, exit status 2
        main(["experiment", "fig3", "--jobs", "0", "--out", str(tmp_path / "x")])
    assert exc.value.code == 2


def test_runs_go_jobs_at_a_time_and_a_stop_request_cancels_those_in_flight(
    tmp_path, monkeypatch, capsys
):
    """Two at a time: the third run starts only when one of the first two ended. A SIGTERM
    to the experiment (delivered to the main thread) cancels the run still in flight (its
    worker stops it), the one not started stays pending, and the exit status is 128 + 15."""
    import signal
    import threading

    from rt_controller.rig.failures import RigCancelled

    started: list[str] = []
    lock = threading.Lock()
    cancelled: list[str] = []

    ended: list[str] = []

    def fake(opts):
        with lock:
            started.append(opts.law)
            first = len(started) == 1
        if first:  # ends at once (whichever of the first two got here first); the third may start
            ended.append(str(opts.log))
            return {"J": 1.0, "f_final_norm": 0.0, "problems": []}
        if len(started) == 3:
            os.kill(os.getpid(), signal.SIGTERM)  # the user stops the experiment
        if not opts.cancel.wait(30):
            raise AssertionError("never cancelled")
        cancelled.append(opts.law)
        raise RigCancelled("cancelled")

    monkeypatch.setattr(ex, "run_rig", fake)
    out = tmp_path / "exp"
    argv = ["experiment", "all", "--reps", "1", "--duration", "1", "--out", str(out), "--jobs", "2"]
    assert main([*argv, "--fresh-processes"]) == 128 + signal.SIGTERM
    assert len(started) == 3 and sorted(cancelled) == sorted(started[1:])
    res = json.loads((out / "results.json").read_text())
    status = [r["status"] for r in res["runs"]]
    # the one that ended (as failed: a fake run writes no log) is one of the first two; the two
    # cancelled and the five never started are pending, none is failed for being stopped
    done = next(i for i, r in enumerate(res["runs"]) if str(out / r["log"]) in ended)
    assert done in (0, 1)
    assert status == ["pending"] * done + ["failed"] + ["pending"] * (7 - done)
    assert [f["run"] for f in res["failures"]] == [res["runs"][done]["name"]]
    assert "interrupted by SIGTERM" in capsys.readouterr().err


def test_runs_sharing_an_emulator_config_share_processes(tmp_path):
    """table1: the horizons (controller sections) and the noise seeds (each scenario reset
    names its run's seed) all share one set of processes, split in two while there are fewer
    sets than jobs; fig3 + fig4 likewise; realtime and --fresh-processes: one run each."""
    _, runs = ex.prepare(settings(tmp_path, ("table1",), reps=2, jobs=2))
    got = [[r.spec.name for r in b] for b in ex.batches(list(runs.values()), settings(tmp_path))]
    names = [f"rhc-T{h}-seed{seed}" for h in ("0.02", "0.1", "1.0") for seed in (0, 1)]
    assert got == [names[:3], names[3:]]
    single = settings(tmp_path, ("table1",), reps=2, jobs=1)
    assert [[r.spec.name for r in b] for b in ex.batches(list(runs.values()), single)] == [names]
    figs = settings(tmp_path / "f", ("fig3", "fig4"), jobs=2)
    _, runs = ex.prepare(figs)
    got = [[r.spec.name for r in b] for b in ex.batches(list(runs.values()), figs)]
    assert got == [["rhc-T0.02", "ioc", "pbc"], ["rhc-T0.1", "rhc-T1.0"]]
    one = settings(tmp_path / "f", ("fig3", "fig4"), jobs=1)
    assert len(ex.batches(list(runs.values()), one)) == 1
    for kw in ({"fresh_processes": True}, {"realtime": True}):
        flat = ex.batches(list(runs.values()), settings(tmp_path, **kw))
        assert [len(b) for b in flat] == [1] * 5


def test_a_plan_that_breaks_off_fails_its_remaining_runs(tmp_path, monkeypatch):
    """The controller printed the first run's summary, then died: that run is recorded as it
    ended (here not clean), the others failed with the controller's error; the plan file
    names every run with its config and log."""
    seen = {}

    def broken(opts, n):
        seen["plan"] = json.loads(opts.plan.read_text())
        first = seen["plan"]["runs"][0]["name"]
        summary = {"run": first, "J": 2.0, "wall_s": 0.5, "problems": ["1 DSP watchdog trip(s)"]}
        return [summary], RigProcessError("controller exited with status 3:\nboom")

    monkeypatch.setattr(ex, "run_rig_plan", broken)
    monkeypatch.setattr(ex, "steady_cost", lambda log: None)
    st = settings(tmp_path, ("fig4",), jobs=1)
    _, runs = ex.prepare(st)
    batch = ex.execute_batch(list(runs.values()), st)
    assert [r["name"] for r in seen["plan"]["runs"]] == ["rhc-T0.02", "rhc-T0.1", "rhc-T1.0"]
    assert all(Path(r["config"]).is_file() for r in seen["plan"]["runs"])
    assert [r.status for r in batch] == ["failed"] * 3
    assert batch[0].error == "run not clean: 1 DSP watchdog trip(s)" and batch[0].J == 2.0
    assert all(r.error.startswith("RigProcessError: controller exited") for r in batch[1:])
    assert all("boom" in r.error and r.J is None for r in batch[1:])


# -------------------------------------------------------------- real daemons (integration)
@pytest.fixture(scope="module")
def table1(tmp_path_factory) -> tuple[Path, dict]:
    """``hil experiment table1 --reps 2 --duration 4`` through the real daemons (lockstep)."""
    out = tmp_path_factory.mktemp("exp") / "table1"
    argv = ["experiment", "table1", "--reps", "2", "--duration", "4", "--out", str(out)]
    assert main(argv) == 0
    assert not live_children(), "the experiment left processes behind"
    return out, json.loads((out / "results.json").read_text())


@pytest.mark.integration
@pytest.mark.slow
def test_table1_writes_report_results_and_logs(table1):
    out, res = table1
    assert (out / "report.md").is_file() and (out / "results.json").is_file()
    rows = res["table1"]["rows"]
    assert [r["horizon_s"] for r in rows] == [0.02, 0.1, 1.0]
    assert [r["steps"] for r in rows] == [10, 10, 20]
    for r in rows:
        assert len(r["J"]) == 2 and all(math.isfinite(j) and j > 0 for j in r["J"])
        assert r["J"][0] != r["J"][1], "repetitions must differ by their sensor noise seed"
        assert r["seeds"] == [0, 1]
        assert r["average"] == pytest.approx(sum(r["J"]) / 2)
    assert res["table1"]["noise_px"] == 0.0 and res["camera_model"] == "image"
    assert res["clock"] == "lockstep" and not res["failures"]
    for run in res["runs"]:
        log = read_log(out / run["log"], raw=False)
        assert log.n_cycles == 200 and not log.truncated  # 4 s at 50 Hz
        assert log.config.camera.seed == run["seed"]
        assert log.config.camera.noise_px == 0.0
    assert (out / "table1_J.png").read_bytes()[:8] == PNG_MAGIC


@pytest.mark.integration
@pytest.mark.slow
def test_table1_markdown_in_report(table1):
    out, res = table1
    report = (out / "report.md").read_text()
    head = "| Horizon length | 1st | 2nd | average |"
    assert head in report and res["table1"]["markdown"] in report
    lines = report.splitlines()
    i = lines.index(head)
    assert lines[i + 1] == "|---|---:|---:|---:|"
    num = r"(\d+\.\d{3})"
    for line, h in zip(lines[i + 2 : i + 5], ("0.02", "0.1", "1.0"), strict=True):
        m = re.fullmatch(rf"\| T = {h} s \| {num} \| {num} \| {num} \|", line)
        assert m, line
        a, b, avg = (float(g) for g in m.groups())
        assert a <= b and avg == pytest.approx((a + b) / 2, abs=1e-3)
    assert "| T = 0.02 s | 3352 | 3357 | 3367 | 3477 | 3486 | 3408 |" in report
    assert "seeds [0, 1]" in report and "lockstep" in report
    assert "the camera sensor's noise, seeds [0, 1]" in report


@pytest.mark.integration
@pytest.mark.slow
def test_fig3_writes_figures(tmp_path, capsys):
    out = tmp_path / "fig3"
    assert main(["experiment", "fig3", "--duration", "2", "--out", str(out), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert set(res["fig3"]["J"]) == {"rhc", "ioc", "pbc"}
    assert all(math.isfinite(j) and j > 0 for j in res["fig3"]["J"].values())
    assert res["fig3"]["figures"] == ["fig3_f.png", "fig3_xi.png", "fig3_u.png"]
    for name in res["fig3"]["figures"]:
        data = (out / name).read_bytes()
        assert data[:8] == PNG_MAGIC and len(data) > 10_000
    report = (out / "report.md").read_text()
    assert "![fig3_f.png](fig3_f.png)" in report
    assert {r["law"] for r in res["runs"]} == {"rhc", "ioc", "pbc"}


@pytest.mark.integration
@pytest.mark.slow
def test_a_failing_daemon_fails_the_experiment_without_leftovers(tmp_path, capsys, monkeypatch):
    # without the up-front check (which refuses this bus before any run) the daemons meet it
    monkeypatch.setattr("rt_controller.commands.experiment.check_shared_bus", lambda s: None)
    out = tmp_path / "fail"
    argv = ["experiment", "table1", "--reps", "1", "--duration", "1", "--out", str(out)]
    assert main([*argv, "--can", "socketcan:hil-no-such-bus"]) == 1
    err = capsys.readouterr().err
    assert "run rhc-T0.02-seed0 (RHC T = 0.02 s, seed 0) failed" in err
    assert "emulator exited with status 2" in err or "controller exited with status 2" in err
    assert not live_children()
    said = (
        r"not run: the (emulator|controller) ended in run rhc-T0\.02-seed0 \(exited with status 2\)"
    )
    assert re.search(said, err), err
    res = json.loads((out / "results.json").read_text())
    assert len(res["failures"]) == 1  # the two runs after it never started: not run


@pytest.mark.integration
@pytest.mark.slow
def test_lockstep_results_do_not_depend_on_jobs_or_on_sharing_processes(tmp_path, capsys):
    """Fresh processes per run, one set for all three (a plan with two scenario resets), and
    two sets at a time give the same runs: J, f_final and every logged state, torque and
    feature bit for bit (lockstep runs are deterministic; each rig has its own bus, zenoh
    port and key; a reset starts a run as fresh processes do)."""
    got, logs = {}, {}
    for how, extra in (("fresh", ["--fresh-processes"]), ("jobs1", ["--jobs", "1"]), ("jobs2", [])):
        out = tmp_path / how
        argv = ["experiment", "fig3", "--duration", "1.5", "--out", str(out)]
        assert main([*argv, *extra, "--json"]) == 0
        res = json.loads(capsys.readouterr().out)
        got[how] = {r["name"]: (r["J"], r["f_final"]) for r in res["runs"]}
        logs[how] = {r["name"]: read_log(out / r["log"], raw=False).cycles for r in res["runs"]}
        assert not live_children()
    assert got["fresh"] == got["jobs1"] == got["jobs2"] and len(got["fresh"]) == 3
    for name, cycles in logs["fresh"].items():
        for how in ("jobs1", "jobs2"):
            for col in ("q", "dq", "f", "tau", "cost"):
                assert cycles[col].tobytes() == logs[how][name][col].tobytes(), (how, name, col)


@pytest.mark.integration
@pytest.mark.slow
def test_a_stop_request_during_a_parallel_sweep_stops_every_rig(tmp_path, capsys):
    """SIGTERM while two rigs run: both are stopped (no process outlives the experiment),
    the exit status is 128 + 15 and what ran is written up."""
    import signal
    import threading
    import time

    def stop_when_both_run() -> None:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if len(live_children()) >= 6:  # two rigs of three processes
                time.sleep(0.5)
                os.kill(os.getpid(), signal.SIGTERM)
                return
            time.sleep(0.05)

    killer = threading.Thread(target=stop_when_both_run, daemon=True)
    killer.start()
    out = tmp_path / "stop"
    argv = ["experiment", "table1", "--reps", "1", "--duration", "30", "--out", str(out)]
    assert main([*argv, "--jobs", "2"]) == 128 + signal.SIGTERM
    killer.join(5)
    assert not live_children(), "a rig outlived the stopped experiment"
    res = json.loads((out / "results.json").read_text())
    assert [r["status"] for r in res["runs"]] == ["pending"] * 3
    assert "interrupted by SIGTERM" in capsys.readouterr().err


def test_the_runs_go_as_tasks_to_an_existing_cluster_with_scheduler(tmp_path, monkeypatch, capsys):
    """``--scheduler``: each batch is a task on that cluster (here one in this process, so the
    fake rig applies); the output folder becomes absolute for the workers; ``--jobs`` is
    refused with it, before anything is written."""
    from distributed import LocalCluster

    seen = []

    def fake(opts):
        seen.append((opts.law, Path(opts.config).is_absolute()))
        return {"J": {"rhc": 1.0, "ioc": 2.0, "pbc": 3.0}[opts.law], "problems": []}

    got = {}

    def outputs(settings, runs_by_exp, runs, command):  # a fake run writes no log to report
        got.update({name: (r.status, r.J) for name, r in runs.items()})
        return {"failures": []}

    monkeypatch.setattr(ex, "run_rig", fake)
    monkeypatch.setattr(ex, "steady_cost", lambda log: None)
    monkeypatch.setattr("rt_controller.rig.experiment_report.write_outputs", outputs)
    monkeypatch.chdir(tmp_path)
    kw = {"processes": False, "protocol": "tcp://", "host": "127.0.0.1", "dashboard_address": None}
    with LocalCluster(n_workers=2, threads_per_worker=1, **kw) as lc:
        at = ["--scheduler", lc.scheduler_address]
        assert main(["experiment", "fig3", "--out", "x", *at, "--jobs", "1"]) == 2
        assert "--jobs sizes the local cluster" in capsys.readouterr().err
        assert not (tmp_path / "x").exists()
        argv = ["experiment", "fig3", "--duration", "1", "--out", "exp", "--fresh-processes"]
        assert main([*argv, *at, "--json"]) == 0
    assert got == {"rhc-T0.02": ("ok", 1.0), "ioc": ("ok", 2.0), "pbc": ("ok", 3.0)}
    assert sorted(seen) == [("ioc", True), ("pbc", True), ("rhc", True)]


def test_the_profile_reaches_every_run_and_cia402_runs_start_their_own_rig(tmp_path):
    """--profile cia402 (or the config's hardware.profile) is each run's hardware.profile;
    its lockstep runs are batches of one: the plan's scenario reset is the emulated DSP's."""
    cia = settings(tmp_path / "p", ("fig3",), profile="cia402", jobs=1)
    _, runs = ex.prepare(cia)
    assert {r.config.hardware.profile for r in runs.values()} == {"cia402"}
    assert {load_config(r.config_file).hardware.profile for r in runs.values()} == {"cia402"}
    assert [len(b) for b in ex.batches(list(runs.values()), cia)] == [1, 1, 1]
    cfg = tmp_path / "cia402.toml"
    cfg.write_text('[hardware]\nprofile = "cia402"\n', encoding="utf-8")
    by_config = settings(tmp_path / "c", ("fig3",), config=str(cfg), jobs=1)
    assert (by_config.hardware_profile(), by_config.shares_processes()) == ("cia402", False)
    dsp = settings(tmp_path / "d", ("fig3",), config=str(cfg), profile="dsp", jobs=1)
    _, runs = ex.prepare(dsp)
    assert {r.config.hardware.profile for r in runs.values()} == {"dsp"}
    assert [len(b) for b in ex.batches(list(runs.values()), dsp)] == [3]


@pytest.mark.integration
@pytest.mark.slow
def test_fig3_runs_on_the_cia402_profile_and_the_report_names_it(tmp_path, capsys):
    out = tmp_path / "fig3-cia402"
    argv = ["experiment", "fig3", "--duration", "2", "--profile", "cia402", "--jobs", "1"]
    assert main([*argv, "--out", str(out), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["profile"] == "cia402" and "--profile cia402" in res["command"]
    assert {r["profile"] for r in res["runs"]} == {"cia402"}
    assert all(math.isfinite(j) and j > 0 for j in res["fig3"]["J"].values())
    assert "Hardware profile: **cia402**" in (out / "report.md").read_text()
