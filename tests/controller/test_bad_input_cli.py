"""Bad input to ``hil`` in-process (``rt_controller.cli.main``): one ``hil CMD: error:`` line,
exit 2 (1 for a failure that is not the user's), never a traceback; nothing is started first."""

from __future__ import annotations

import errno
import os
import socket
import threading
from pathlib import Path

import pytest

from hal.zenoh_session import free_loopback_port
from rt_controller.cli import main

SWEEP_SPEC = '[study]\nduration_s = 0.2\nrepetitions = 1\n[[axes]]\nkey = "gains.kp"\n'
SWEEP_SPEC += "values = [0.1, 0.2]\n"


def hil(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """Exit status, stdout and the stderr lines that say ``error:``."""
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    out, err = capsys.readouterr()
    assert "Traceback" not in err, err
    return code, out, "\n".join(ln for ln in err.splitlines() if "error:" in ln)


def nowhere() -> list[str]:
    """A loopback endpoint no hub listens on: a ``hil param`` that got through would wait."""
    return ["--zenoh-endpoint", f"tcp/127.0.0.1:{free_loopback_port()}"]


def refused(argv: list[str], capsys: pytest.CaptureFixture[str], *names: str) -> str:
    """``argv`` ends in exit 2 and one error line naming each of ``names``."""
    code, _, err = hil(argv, capsys)
    assert code == 2 and len(err.splitlines()) == 1 and err.startswith("hil"), (code, err)
    for name in names:
        assert name in err, err
    return err


@pytest.fixture
def nothing_starts(monkeypatch: pytest.MonkeyPatch) -> None:
    """The benches, the emulator and the closed loop fail the test if a bad option reaches them."""

    def started(*_: object, **__: object) -> None:
        raise AssertionError("a bad option was not refused before the work started")

    import plant_emulator.entry
    import rt_controller.rig.bench_loop
    import rt_controller.rig.bench_tuning
    import rt_controller.rig.bench_vision

    monkeypatch.setattr(plant_emulator.entry, "run_emulator", started)
    monkeypatch.setattr(rt_controller.rig.bench_loop, "bench_loop", started)
    monkeypatch.setattr(rt_controller.rig.bench_vision, "bench_vision", started)
    monkeypatch.setattr(rt_controller.rig.bench_tuning, "bench_tuning", started)


# -- F7: OSError from a path the user gave ---------------------------------------------------


@pytest.mark.parametrize(
    ("code", "status"),
    [
        (errno.ENOENT, 2),
        (errno.EISDIR, 2),
        (errno.EEXIST, 2),
        (errno.EACCES, 2),
        (errno.EROFS, 2),
        (errno.ENOSPC, 1),
        (errno.EIO, 1),
    ],
)
def test_run_standalone_turns_an_os_error_into_one_line(code, status, capsys):
    from hal.signals import run_standalone

    def body() -> int:
        raise OSError(code, os.strerror(code), "/some/where/x.toml")

    assert run_standalone("hil param", body) == status
    err = capsys.readouterr().err
    assert err == f"hil param: error: /some/where/x.toml: {os.strerror(code)}\n"


def test_sweep_out_an_existing_file(tmp_path, capsys):
    spec = tmp_path / "ok.toml"
    spec.write_text(SWEEP_SPEC)
    out = tmp_path / "taken.mcap"
    out.write_text("x")
    refused(["sweep", str(spec), "--no-progress", "--out", str(out)], capsys, str(out))


def test_bench_tuning_workdir_a_file(tmp_path, capsys, nothing_starts):
    work = tmp_path / "a-file"
    work.write_text("x")
    refused(["bench", "tuning", "--workdir", str(work), "--requests", "1"], capsys, str(work))


@pytest.mark.parametrize("where", ["a-dir", "a-file/x.toml"])
def test_camera_calibrate_write_a_bad_path_is_refused_first(where, tmp_path, capsys):
    (tmp_path / "a-dir").mkdir()
    (tmp_path / "a-file").write_text("x")
    target = str(tmp_path / where)
    argv = ["camera", "calibrate", "--source", "emulated", "--views", "3", "--write", target]
    refused(argv, capsys, "--write", target)


def test_camera_calibrate_write_failure_keeps_the_calibration(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[gains]\nkp = nan\n")  # TOML, but not a valid config
    argv = ["camera", "calibrate", "--source", "emulated", "--views", "3", "--write", str(bad)]
    code, out, err = hil([*argv, "--json"], capsys)
    assert code == 2 and len(err.splitlines()) == 1, err
    assert str(bad) in err and ".calibrating" not in err, err
    assert '"fx"' in out  # the calibration is printed, not lost
    assert bad.read_text() == "[gains]\nkp = nan\n"
    assert not list(tmp_path.glob("*.calibrating"))


# -- F6: numeric options -------------------------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "names"),
    [
        (["simulate", "--law", "rhc", "--horizon", "nan"], ("horizon",)),
        (["simulate", "--law", "rhc", "--horizon", "inf"], ("horizon",)),
        (["simulate", "--duration", "0.001"], ("--duration", "control period")),
        (["simulate", "--rate", "3", "--duration", "0.3"], ("--duration", "control period")),
        (["param", "get", "--timeout", "-1"], ("--timeout",)),
        (["param", "get", "--timeout", "nan"], ("--timeout",)),
        (["param", "get", "--timeout", "0"], ("--timeout",)),
        (["camera", "calibrate", "--source", "emulated", "--square-mm", "inf"], ("--square-mm",)),
        (
            ["camera", "calibrate", "--source", "emulated", "--views", "3", "--square-mm", "1000"],
            ("--marker-mm",),
        ),
        (["camera", "calibrate", "--source", "emulated", "--seed", "-1"], ("--seed",)),
        (
            ["camera", "calibrate", "--source", "emulated", "--squares", "10000", "10000"],
            ("--squares",),
        ),
        (["camera", "calibrate", "--source", "emulated", "--squares", "21", "10"], ("--squares",)),
    ],
    ids=lambda v: " ".join(v) if isinstance(v, list) else None,
)
def test_numeric_option_out_of_range(argv, names, capsys):
    refused([*argv, *nowhere()] if argv[0] == "param" else argv, capsys, *names)


# -- F8: a --scheduler that speaks another protocol ------------------------------------------


def test_scheduler_answering_garbage_is_one_line():
    from rt_controller.errors import ControllerConfigError
    from rt_controller.sweep.executor import open_cluster

    server = socket.create_server(("127.0.0.1", 0))  # loopback only
    port = server.getsockname()[1]
    done = threading.Event()

    def answer() -> None:
        server.settimeout(0.2)
        while not done.is_set():
            try:
                conn, _ = server.accept()
            except OSError:
                continue
            with conn:
                conn.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n" * 4)

    thread = threading.Thread(target=answer, daemon=True)
    thread.start()
    try:
        with pytest.raises(ControllerConfigError, match="cannot connect"):
            open_cluster(scheduler=f"tcp://127.0.0.1:{port}")
    finally:
        done.set()
        thread.join()
        server.close()


# -- F12: hil param ---------------------------------------------------------------------------


def test_param_get_unknown_key(capsys):
    err = refused(
        ["param", "get", "gains.kp", "nosuchkey", *nowhere()], capsys, "nosuchkey", "gains.kp"
    )
    assert "gains.kp" in err.split("nosuchkey", 1)[1]  # the known keys are listed after it


def test_param_at_tick_negative(capsys):
    refused(["param", "set", "gains.kp=0.2", "--at-tick", "-5", *nowhere()], capsys, "--at-tick")


# -- F14: a config that is not a regular file ---------------------------------------------------


@pytest.mark.parametrize("kind", ["fifo", "char device", "directory"])
def test_config_not_a_regular_file(kind, tmp_path, capsys):
    path = tmp_path / "cfg.toml"
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "directory":
        path.mkdir()
    else:
        path = Path("/dev/zero")
    refused(["simulate", "--config", str(path)], capsys, str(path))


# -- F15: options accepted without validation --------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "names"),
    [
        (["emulator", "--vision-wait", "nan"], ("--vision-wait",)),
        (["emulator", "--vision-wait", "inf"], ("--vision-wait",)),
        (["replay", "x.mcap", "--republish", "--wait-subscriber", "-1"], ("--wait-subscriber",)),
        (["replay", "x.mcap", "--republish", "--lead-in", "nan"], ("--lead-in",)),
        (["replay", "x.mcap", "--republish", "--lead-in", "-1"], ("--lead-in",)),
        (["replay", "x.mcap", "--republish", "--speed", "inf"], ("--speed",)),
        (["replay", "x.mcap", "--republish", "--out", "y.mcap"], ("--out", "--republish")),
        (["bench", "vision", "--lockstep-duration", "-1"], ("--lockstep-duration",)),
        (["bench", "vision", "--realtime-duration", "nan"], ("--realtime-duration",)),
        (["bench", "loop", "--monitor-port", "99999"], ("--monitor-port",)),
        (["bench", "loop", "--lockstep-duration", "nan"], ("--lockstep-duration",)),
    ],
    ids=lambda v: " ".join(v) if isinstance(v, list) else None,
)
def test_unvalidated_option_refused(argv, names, capsys, nothing_starts):
    refused(argv, capsys, *names)


@pytest.mark.parametrize(
    "argv",
    [
        ["up", "--lockstep", "--duration", "1"],
        ["controller", "--no-rt", "--duration", "1"],
        ["emulator", "--duration", "0.5"],
        ["experiment", "fig3", "--reps", "1"],
    ],
)
def test_python_cans_in_process_bus_is_refused_between_processes(
    argv, tmp_path, capsys, monkeypatch
):
    """The rig's daemons are separate processes: on python-can's ``virtual`` bus they would
    wait for peers they never hear (``hil up`` reported "no joint state" after 20 s)."""
    import rt_controller.rig.processes

    def started(*_: object, **__: object) -> None:
        raise AssertionError("a rig was started on an in-process bus")

    monkeypatch.setattr(rt_controller.rig.processes, "run_rig", started)
    monkeypatch.chdir(tmp_path)
    assert main(["keygen", "rig.key"]) == 0
    capsys.readouterr()
    key = ["--key-file", "rig.key"] if argv[0] in ("controller", "emulator") else []
    err = refused([*argv, "--can", "virtual", *key], capsys, "virtual", "udp_multicast")
    assert "one process only" in err
    assert not list(tmp_path.glob("experiments/*")) and not list(tmp_path.glob("logs/*"))


def test_replay_set_takes_each_key_once(tmp_path, capsys):
    """``hil replay --set gains.kp=0.2 --set gains.kp=0.3`` replayed with 0.3 without a word."""
    log = tmp_path / "any.mcap"
    log.write_bytes(b"")  # the sets are refused before the log is read
    argv = ["replay", str(log), "--set", "gains.kp=0.2", "--set", "gains.kp=0.3"]
    refused(argv, capsys, "--set: gains.kp given twice")
