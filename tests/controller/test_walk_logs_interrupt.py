"""``hil replay``, ``hil recover`` and ``hil export`` stopped by Ctrl-C (SIGINT) or SIGTERM in
the middle of their work: one line on stderr, exit 130 (143), no output file cut short (and no
leftover temporary one), an existing output file as it was, the input log untouched.

The signal is sent by the process to itself from a public function it calls while it writes
(a replayed tick, a copied message, an export file), so it lands mid-work every time.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from hal.config import RigConfig
from tests.controller.test_replay import record_run

REPO = Path(__file__).resolve().parents[2]

PATCHES = {
    "replay": """
        from rt_controller.logtools import replay_out
        orig = replay_out.OutLog.cycle
        def cycle(self, record):
            hit()
            return orig(self, record)
        replay_out.OutLog.cycle = cycle
    """,
    "recover": """
        from mcap.writer import Writer
        orig = Writer.add_message
        def add_message(self, *a, **k):
            hit()
            return orig(self, *a, **k)
        Writer.add_message = add_message
    """,
    "export": """
        import contextlib
        from rt_controller.logs import export
        orig = export.written_whole
        @contextlib.contextmanager
        def written_whole(path):
            with orig(path) as tmp:
                yield tmp
                hit()  # the second file is written in full, then the signal, then no rename
        export.written_whole = written_whole
    """,
}

SCRIPT = """
import os, signal, sys
sig, at, argv = getattr(signal, sys.argv[1]), int(sys.argv[2]), sys.argv[3:]
calls = [0]
def hit():
    calls[0] += 1
    if calls[0] == at:
        os.kill(os.getpid(), sig)
{patch}
from rt_controller.cli import main
sys.exit(main(argv))
"""


def run_signalled(cmd: str, sig: str, at: int, *argv: str | Path) -> subprocess.CompletedProcess:
    script = SCRIPT.format(patch=textwrap.dedent(PATCHES[cmd]))
    return subprocess.run(
        [sys.executable, "-c", script, sig, str(at), cmd, *map(str, argv)],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
        cwd=REPO,
    )


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    return record_run(tmp_path_factory.mktemp("walk_logs") / "run.mcap", RigConfig())


def status(sig: str) -> int:
    return {"SIGINT": 130, "SIGTERM": 143}[sig]


def one_line(done: subprocess.CompletedProcess, prog: str, sig: str) -> str:
    assert done.returncode == status(sig), (done.returncode, done.stderr)
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith(f"{prog}: interrupted by {sig}"), lines
    return lines[0]


def no_leftovers(folder: Path) -> None:
    assert not [p for p in folder.iterdir() if p.name.endswith(".partial")]


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_replay_out_interrupted(log, tmp_path, sig):
    before = log.read_bytes()
    out = tmp_path / "new.mcap"
    done = run_signalled("replay", sig, 10, log, "--out", out, "-q")
    line = one_line(done, "hil replay", sig)
    assert str(out) in line and "not written" in line
    assert not out.exists()
    no_leftovers(tmp_path)
    assert log.read_bytes() == before


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_replay_out_interrupted_keeps_the_file_it_would_replace(log, tmp_path, sig):
    out = tmp_path / "old.mcap"
    out.write_bytes(b"an older replay")
    done = run_signalled("replay", sig, 10, log, "--out", out, "--force", "-q")
    one_line(done, "hil replay", sig)
    assert out.read_bytes() == b"an older replay"
    no_leftovers(tmp_path)


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_recover_interrupted(log, tmp_path, sig):
    data = log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    out = tmp_path / "copy.mcap"
    done = run_signalled("recover", sig, 50, cut, "--out", out)
    line = one_line(done, "hil recover", sig)
    assert str(out) in line and "not written" in line
    assert not out.exists()
    no_leftovers(tmp_path)
    assert cut.read_bytes() == data[: len(data) * 2 // 3]


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_export_interrupted_names_what_was_written(log, tmp_path, sig):
    pytest.importorskip("pandas")
    out = tmp_path / "csv"
    done = run_signalled("export", sig, 2, log, "--format", "csv", "--out", out)
    line = one_line(done, "hil export", sig)
    written = sorted(p.name for p in out.iterdir())
    assert written == ["run.cycle.csv"], written  # the first file whole, no other
    assert "run.cycle.csv" in line and "run.diagnostics.csv" in line and "run.can.csv" in line
    no_leftovers(out)
    assert os.path.getsize(out / "run.cycle.csv") > 0
