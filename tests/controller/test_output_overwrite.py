"""An explicit output path naming an existing file: a run's log and a log written by ``hil
replay`` or ``hil recover`` are refused (one line, exit 2, before any work) unless ``--force``;
derived outputs (``hil export``, ``hil param dump``) are replaced, as their help says; an
experiment's "run again" commands run again and again without touching the run's log."""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from hal.config import RigConfig
from rt_controller.cli import main
from tests.controller.test_replay import record_run

HIL = str(Path(sys.executable).parent / "hil")


def hil(*argv: str | Path, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [HIL, *map(str, argv)], capture_output=True, text=True, timeout=300, check=False, cwd=cwd
    )


@pytest.fixture(scope="module")
def log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return record_run(tmp_path_factory.mktemp("ow") / "run.mcap", RigConfig())


@pytest.fixture
def existing(tmp_path: Path) -> Path:
    """A previous run's log, somewhere a new one is asked to go."""
    path = tmp_path / "previous.mcap"
    path.write_bytes(b"a previous run's log")
    return path


def refused(done: subprocess.CompletedProcess[str], cmd: str, option: str, path: Path) -> None:
    assert done.returncode == 2, done.stderr
    line = f"hil {cmd}: error: {option} {path}: exists (pass --force to replace it)\n"
    assert done.stderr == line


def test_up_refuses_an_existing_log_before_starting_the_rig(existing):
    done = hil("up", "--lockstep", "--duration", "1", "--log", existing)
    refused(done, "up", "--log", existing)
    assert done.stdout == "" and existing.read_bytes() == b"a previous run's log"


@pytest.mark.integration
def test_up_force_replaces_the_log_and_its_controller_writes_it(existing):
    """``hil up`` checked the path once; its controller child must not refuse it."""
    done = hil("up", "--lockstep", "--duration", "0.2", "--log", existing, "--force", "--json")
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["log"] == str(existing) and summary["ticks"] >= 1
    assert existing.read_bytes()[:8] == b"\x89MCAP0\r\n"


def test_controller_refuses_an_existing_log_before_its_daemon(existing):
    done = hil("controller", "--can", "virtual", "--no-rt", "--duration", "1", "--log", existing)
    refused(done, "controller", "--log", existing)
    assert existing.read_bytes() == b"a previous run's log"


def test_replay_out_refuses_an_existing_file_unless_forced(log, existing, capsys):
    assert main(["replay", str(log), "--out", str(existing)]) == 2
    err = capsys.readouterr().err
    assert err == f"hil replay: error: --out {existing}: exists (pass --force to replace it)\n"
    assert existing.read_bytes() == b"a previous run's log"
    assert main(["replay", str(log), "--out", str(existing), "--force", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["ok"]
    assert existing.read_bytes()[:8] == b"\x89MCAP0\r\n"


def test_replay_force_still_never_overwrites_the_log_it_replays(log, capsys):
    before = log.read_bytes()
    assert main(["replay", str(log), "--out", str(log), "--force"]) == 2
    assert "overwrite" in capsys.readouterr().err  # the replay's own reason
    assert log.read_bytes() == before


def test_recover_refuses_an_existing_copy_unless_forced(log, existing, tmp_path, capsys):
    assert main(["recover", str(log), "--out", str(existing)]) == 2
    err = capsys.readouterr().err
    assert err == f"hil recover: error: --out {existing}: exists (pass --force to replace it)\n"
    assert existing.read_bytes() == b"a previous run's log"
    assert main(["recover", str(log), "--out", str(existing), "--force"]) == 0
    assert existing.read_bytes()[:8] == b"\x89MCAP0\r\n"
    cut = tmp_path / "cut.mcap"  # the default copy, LOG.recovered.mcap, as well
    cut.write_bytes(log.read_bytes())
    default = tmp_path / "cut.recovered.mcap"
    default.write_bytes(b"an earlier recovery")
    capsys.readouterr()
    assert main(["recover", str(cut)]) == 2
    assert f"{default}: exists (pass --force" in capsys.readouterr().err
    assert default.read_bytes() == b"an earlier recovery"
    assert main(["recover", str(cut), "--force"]) == 0


def test_recover_force_still_never_overwrites_its_input(log, capsys):
    before = log.read_bytes()
    assert main(["recover", str(log), "--out", str(log), "--force"]) == 2
    err = capsys.readouterr().err
    assert "overwrite" in err and "--force" not in err and log.read_bytes() == before


def test_export_refuses_a_folder_named_like_another_formats_file(log, tmp_path, capsys):
    pytest.importorskip("scipy.io")
    out = tmp_path / "m.csv"
    assert main(["export", str(log), "--format", "mat", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"hil export: error: --out {out}: names a .csv file, but --format mat")
    assert len(err.splitlines()) == 1 and not out.exists()


def test_export_replaces_its_own_files_as_its_help_says(log, tmp_path, capsys):
    pytest.importorskip("scipy.io")
    out = tmp_path / "m.mat"
    out.write_bytes(b"an earlier export")
    assert main(["export", str(log), "--format", "mat", "--out", str(out)]) == 0
    assert out.read_bytes() != b"an earlier export"
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main(["export", "--help"])
    assert "existing files are replaced" in " ".join(capsys.readouterr().out.split())


@pytest.mark.parametrize(
    ("cmd", "words"),
    [
        ("up", "replace an existing --log file"),
        ("controller", "replace an existing --log file"),
        ("replay", "replace an existing --out file"),
        ("recover", "replace an existing copy"),
        ("param", "an existing FILE is replaced"),
    ],
)
def test_help_says_what_happens_to_an_existing_file(cmd, words, capsys):
    with pytest.raises(SystemExit) as exc:
        main([cmd, "--help"])
    assert exc.value.code == 0
    assert words in " ".join(capsys.readouterr().out.split())


@pytest.mark.integration
@pytest.mark.slow
def test_an_experiments_run_again_commands_run_twice_and_keep_the_runs_log(tmp_path):
    pytest.importorskip("dask")
    out = tmp_path / "exp"
    done = hil("experiment", "fig3", "--duration", "0.2", "--jobs", "1", "--out", out, "-q")
    assert done.returncode in (0, 1), done.stderr
    report = (out / "report.md").read_text(encoding="utf-8")
    command = next(line for line in report.splitlines() if re.match(r"hil .* up ", line))
    argv = shlex.split(command)[1:]
    log = out / argv[argv.index("--target-of") + 1]
    before = log.read_bytes()
    for _ in range(2):
        again = hil(*argv, "--json", cwd=out)
        assert again.returncode in (0, 1) and json.loads(again.stdout)["ticks"] >= 1, again.stderr
    assert log.read_bytes() == before
