"""Commands that tell the truth (issue 25, part 5): unusable output paths and logs that are not
hil logs are one line and exit 2 before any work starts, every error carries its ``hil CMD:``
prefix once, ``hil --version`` exists, and slow commands say what they are doing on stderr
while stdout stays the summary scripts parse."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from rt_controller.cli import main

HIL = [sys.executable, "-m", "rt_controller.cli"]


def _one_error_line(err: str, prog: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"{prog}: error: "), err
    assert lines[0].count(f"{prog}:") == 1, err
    return lines[0]


@pytest.fixture
def hil_log(tmp_path, cfg) -> Path:
    from rt_controller.runtime.recorder import CycleRecorder

    path = tmp_path / "run.mcap"
    with CycleRecorder(path, cfg, run_info={"law": "ioc"}) as rec:
        for i in range(20):
            rec.record_cycle({"tick": i, "t_ns": 1 + i * 20_000_000, "u": [0.0, 0.0]})
    return path


# --- unusable output paths -------------------------------------------------------------------

UNUSABLE = {
    "a file": lambda t: str(_a_file(t)),
    "under a file": lambda t: str(_a_file(t) / "sub"),
    "under /proc": lambda t: "/proc/hil-nope/sub",
}


def _a_file(tmp_path: Path) -> Path:
    path = tmp_path / "README.md"
    path.write_text("not a directory\n")
    return path


@pytest.mark.parametrize("where", sorted(UNUSABLE))
def test_report_plot_into_an_unusable_place_is_one_line(hil_log, tmp_path, capsys, where):
    target = UNUSABLE[where](tmp_path)
    assert main(["report", str(hil_log), "--plot", target]) == 2
    line = _one_error_line(capsys.readouterr().err, "hil report")
    assert f"--plot {target}" in line
    assert capsys.readouterr().out == ""  # refused before the report was printed


@pytest.mark.parametrize("where", sorted(UNUSABLE))
def test_experiment_out_unusable_is_refused_before_any_run(tmp_path, where):
    target = UNUSABLE[where](tmp_path)
    done = subprocess.run(
        [*HIL, "experiment", "fig3", "--duration", "0.2", "--out", target],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2, done.stderr
    line = _one_error_line(done.stderr, "hil experiment")
    assert f"--out {target}" in line
    assert "runs (" not in done.stderr  # no sweep started


def test_replay_out_unusable_is_one_line(hil_log, tmp_path, capsys):
    target = str(_a_file(tmp_path) / "new.mcap")
    assert main(["replay", str(hil_log), "--out", target]) == 2
    line = _one_error_line(capsys.readouterr().err, "hil replay")
    assert "--out" in line and "README.md" in line and "not a directory" in line


def test_controller_log_unusable_is_refused_before_the_daemon(tmp_path, capsys):
    target = "/proc/hil-nope/run.mcap"
    assert main(["controller", "--log", target, "--duration", "1", "--no-rt"]) == 2
    line = _one_error_line(capsys.readouterr().err, "hil controller")
    assert "--log" in line and "/proc/hil-nope" in line


@pytest.mark.parametrize("profile", ["dsp", "cia402"])
def test_a_can_interface_that_cannot_open_makes_no_log(tmp_path, profile):
    """A CAN interface that is not there (no such device, or no SocketCAN in the kernel) is
    refused before the recorder starts: one line, exit 2, and no log of a run that never was
    (with ``--force``, an earlier log under the name stays)."""
    key, log = tmp_path / "rig.key", tmp_path / "run.mcap"
    assert main(["keygen", str(key)]) == 0
    log.write_bytes(b"an earlier run")
    argv = ["controller", "--can", "socketcan:hilnope0", "--key-file", str(key)]
    argv += ["--profile", profile, "--log", str(log), "--force", "--duration", "1", "--no-rt"]
    done = subprocess.run([*HIL, *argv], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("hil controller: error: cannot open CAN interface socketcan:hilnope0")
    assert log.read_bytes() == b"an earlier run"


def test_a_can_interface_that_cannot_open_leaves_no_default_log(tmp_path):
    """Without ``--log`` the controller claims ``logs/run-*.mcap`` at start (one name per run);
    a run that never opened its CAN link gives the name back: no empty file is left."""
    key = tmp_path / "rig.key"
    assert main(["keygen", str(key)]) == 0
    argv = ["controller", "--can", "socketcan:hilnope0", "--key-file", str(key)]
    done = subprocess.run(
        [*HIL, *argv, "--duration", "1", "--no-rt"],
        capture_output=True, text=True, timeout=120, cwd=tmp_path,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert list(tmp_path.glob("logs/*")) == []


@pytest.mark.parametrize("command", ["controller", "up"])
@pytest.mark.parametrize("what", ["empty", "fifo"])
def test_a_log_path_that_cannot_hold_a_log_is_refused(tmp_path, capsys, command, what):
    """An empty ``--log`` (it fell back to the default name) and one that exists as something
    other than a regular file (a FIFO here, a device such as /dev/null alike: the log would be
    thrown away by a run called clean) are refused before anything starts."""
    target = ""
    if what == "fifo":
        target = str(tmp_path / "pipe.mcap")
        os.mkfifo(target)
    try:
        rc = main([command, "--log", target, "--duration", "1"])
    except SystemExit as stop:  # an empty path: refused while the command line is parsed
        rc = stop.code
    assert rc == 2
    err = capsys.readouterr().err
    line = _one_error_line(err.splitlines()[-1] if what == "empty" else err, f"hil {command}")
    assert ("the path is empty" if what == "empty" else "is not a regular file") in line, line


def test_a_run_of_no_tick_is_refused(capsys):
    """Shorter than one control period: no tick would run, and a run of none is no clean run."""
    assert main(["up", "--lockstep", "--duration", "0.01"]) == 2
    line = _one_error_line(capsys.readouterr().err, "hil up")
    assert "shorter than one control period (0.02 s at 50 Hz)" in line, line


def test_a_monitor_port_out_of_range_is_refused(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["up", "--monitor-port", "99999"])
    assert exit_info.value.code == 2
    assert "port must be in [0, 65535], got 99999" in capsys.readouterr().err


def test_bench_loop_keep_unusable_is_refused_before_measuring(tmp_path):
    target = str(_a_file(tmp_path))
    done = subprocess.run(
        [*HIL, "bench", "loop", "--keep", target, "--rates", "50", "--duration", "0.5"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert done.returncode == 2, done.stderr
    line = _one_error_line(done.stderr, "hil bench loop")
    assert f"--keep {target}" in line and "not a directory" in line


def test_output_dir_creates_a_usable_directory(tmp_path):
    from rt_controller.commands.output import output_dir, output_file

    made = output_dir(tmp_path / "a" / "b", "--out")
    assert made.is_dir()
    assert output_file(tmp_path / "c" / "x.mcap", "--log") == tmp_path / "c" / "x.mcap"
    assert (tmp_path / "c").is_dir()


# --- logs that are not hil logs --------------------------------------------------------------


def _foreign_mcap(tmp_path: Path) -> Path:
    """An MCAP file another tool wrote: valid, finished, with its own topic and schema."""
    from mcap.writer import Writer

    path = tmp_path / "foreign.mcap"
    with path.open("wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="some-other-tool")
        sid = w.register_schema("camera.Image", "jsonschema", b'{"type": "object"}')
        cid = w.register_channel("/camera/image", "json", sid)
        for i in range(5):
            w.add_message(cid, log_time=i, data=b'{"w": 640}', publish_time=i)
        w.finish()
    return path


def _cut_hil_log(hil_log: Path, tmp_path: Path) -> Path:
    """A hil log cut after its header: no record of the run survives."""
    path = tmp_path / "cut.mcap"
    path.write_bytes(hil_log.read_bytes()[:40])
    return path


NOT_HIL = {
    "an MCAP of another tool": lambda log, t: (_foreign_mcap(t), "not a hil log"),
    "a hil log cut after its header": lambda log, t: (_cut_hil_log(log, t), "not a hil log"),
    "an empty file": lambda log, t: (
        _written(t, b""),
        "empty file (0 bytes): nothing was recorded",
    ),
    "a text file": lambda log, t: (_written(t, b"hello\n"), "not an MCAP file"),
}


def _written(tmp_path: Path, data: bytes) -> Path:
    path = tmp_path / "bad.mcap"
    path.write_bytes(data)
    return path


@pytest.mark.parametrize("command", ["report", "replay"])
@pytest.mark.parametrize("case", sorted(NOT_HIL))
def test_a_log_that_is_not_a_hil_log_is_exit_2(hil_log, tmp_path, capsys, command, case):
    path, why = NOT_HIL[case](hil_log, tmp_path)
    assert main([command, str(path)]) == 2
    line = _one_error_line(capsys.readouterr().err, f"hil {command}")
    assert str(path) in line and why in line
    if case == "an MCAP of another tool":
        assert "no /controller/cycle records" in line and "/camera/image" in line


def test_an_empty_hil_log_is_still_a_hil_log(tmp_path, cfg, capsys):
    from rt_controller.runtime.recorder import CycleRecorder

    path = tmp_path / "empty.mcap"
    CycleRecorder(path, cfg).close()
    assert main(["report", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["ticks"] == 0


# --- one prefix, a version -------------------------------------------------------------------


def test_no_rig_key_names_the_command_once(monkeypatch, capsys):
    monkeypatch.delenv("HIL_KEY_FILE", raising=False)
    assert main(["controller", "--duration", "1", "--no-rt"]) == 2
    line = _one_error_line(capsys.readouterr().err, "hil controller")
    assert line.startswith("hil controller: error: no rig key configured")
    assert "hil keygen" in line


def test_a_message_that_already_names_the_command_is_not_prefixed_twice(capsys):
    from hal.errors import HalError
    from hal.signals import run_standalone

    def body() -> int:
        raise HalError("hil thing: it broke")

    assert run_standalone("hil thing", body) == 2
    assert capsys.readouterr().err == "hil thing: error: it broke\n"


def test_version(capsys):
    from importlib.metadata import version

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"hil {version('hil-rhc-visual-servo')}"


# --- progress on stderr, the summary on stdout -----------------------------------------------


def _hil(*argv: str, progress_after: str | None = "0") -> subprocess.CompletedProcess:
    env = dict(os.environ)
    if progress_after is not None:
        env["HIL_PROGRESS_AFTER_S"] = progress_after
    return subprocess.run([*HIL, *argv], capture_output=True, text=True, timeout=120, env=env)


def test_simulate_json_stays_json_and_progress_goes_to_stderr():
    done = _hil("simulate", "--law", "ioc", "--duration", "1", "--json")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["ticks"] == 50  # stdout is exactly the JSON summary
    lines = done.stderr.strip().splitlines()
    assert any(ln.startswith("hil simulate: ") and "numba" in ln for ln in lines), done.stderr
    assert any("1 s of closed loop" in ln for ln in lines), done.stderr
    assert all(ln.startswith("hil simulate: ") for ln in lines), done.stderr  # plain lines


def test_quiet_silences_the_progress():
    done = _hil("simulate", "--law", "ioc", "--duration", "0.5", "--json", "--quiet")
    assert done.returncode == 0 and done.stderr == "", done.stderr
    assert json.loads(done.stdout)["ticks"] == 25


def test_bench_solver_says_what_it_measures():
    done = _hil("bench", "solver", "--updates", "3")
    assert done.returncode == 0, done.stderr
    json.loads(done.stdout)
    assert "hil bench solver: " in done.stderr and "updates" in done.stderr, done.stderr


def test_progress_waits_before_speaking(capsys):
    """A stage that ends before the threshold prints nothing: quick commands stay quiet."""
    from rt_controller.commands.progress import Progress

    progress = Progress("hil x", after_s=30.0)
    with progress.stage("quick"):
        pass
    assert capsys.readouterr().err == ""
    slow = Progress("hil x", after_s=0.0)
    with slow.stage("slow work"):
        pass
    err = capsys.readouterr().err
    assert err.startswith("hil x: slow work") and "done" in err


@pytest.mark.parametrize(
    "args", [["info", "--json"], ["report", "-q"], ["info"]], ids=["info-json", "report", "info"]
)
def test_output_into_a_closed_pipe_ends_quietly(hil_log, args):
    """``hil info LOG --json | head -0``: the reader is gone before the first write. The
    command ends as a Unix filter does (status 128 + SIGPIPE), without a line on stderr; also
    what rich prints (``hil report``: rich's own answer was a silent exit 1)."""
    r, w = os.pipe()
    os.close(r)
    try:
        done = subprocess.run(
            [*HIL, *args, str(hil_log)],
            stdout=w,
            capture_output=False,
            stderr=subprocess.PIPE,
            text=True,
            timeout=120,
        )
    finally:
        os.close(w)
    assert (done.returncode, done.stderr) == (141, "")
