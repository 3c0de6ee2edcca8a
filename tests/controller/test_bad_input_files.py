"""Bad files and paths given to the offline commands: a FIFO or non-UTF-8 study spec is one line
(never a hang or Python's codec text), a full disk leaves no half ``replay --out`` log, an MCAP
whose only hil trait is a ``/controller/cycle`` channel of unreadable records is not a hil log
(exit 2, the count named; a hil log with its run metadata is a damaged one, see
test_log_truth.py), and an empty ``--out``/``--log`` path is refused, not taken as the default."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.writer import Writer

from hal.config import RigConfig
from rt_controller.cli import main
from tests.controller.test_replay import record_run

CYCLE = "/controller/cycle"


def _hil(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "rt_controller.cli", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


def test_a_fifo_study_spec_is_refused_not_waited_on(tmp_path):
    fifo = tmp_path / "study.toml"
    os.mkfifo(fifo)
    done = _hil("sweep", str(fifo), "--out", str(tmp_path / "out"), timeout=30)
    assert done.returncode == 2
    assert done.stderr.strip() == f"hil sweep: error: cannot read spec {fifo}: not a regular file"


def test_a_non_utf8_study_spec_names_the_byte(tmp_path, capsys):
    spec = tmp_path / "study.toml"
    spec.write_bytes(b'[study]\nname = "\xff"\n')
    assert main(["sweep", str(spec), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"hil sweep: error: {spec}: not UTF-8 text (invalid byte 0xff at offset 16)"


@pytest.fixture(scope="module")
def big_run(tmp_path_factory) -> Path:
    """A log whose replay (> 500 KB) cannot fit the 192 KiB ``tiny_tmpfs``."""
    return record_run(tmp_path_factory.mktemp("big") / "run.mcap", RigConfig(), 1500)


def test_a_disk_filling_up_leaves_no_half_replay_log(big_run, tiny_tmpfs, capsys):
    old = tiny_tmpfs / "old.mcap"
    old.write_text("the log --force would have replaced\n")
    assert main(["replay", "-q", str(big_run), "--out", str(old), "--force"]) == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last == f"hil replay: error: cannot write {old}: [Errno 28] No space left on device"
    assert list(tiny_tmpfs.iterdir()) == [old]  # no half log, the old one kept
    assert old.read_text() == "the log --force would have replaced\n"


def test_a_full_disk_leaves_no_empty_replay_log(big_run, tiny_tmpfs, capsys):
    filler = tiny_tmpfs / "filler"
    with filler.open("wb") as fh, contextlib.suppress(OSError):
        fh.write(bytes(256 * 1024))
    out = tiny_tmpfs / "new.mcap"
    assert main(["replay", "-q", str(big_run), "--out", str(out)]) == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith(f"hil replay: error: cannot create MCAP log {out}: ")
    assert list(tiny_tmpfs.iterdir()) == [filler]


def _log_of_bad_cycles(path: Path, payloads: list[bytes]) -> Path:
    with path.open("wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="test")
        schema = w.register_schema(name="cycle", encoding="jsonschema", data=b"{}")
        channel = w.register_channel(topic=CYCLE, message_encoding="json", schema_id=schema)
        for i, data in enumerate(payloads):
            w.add_message(channel, log_time=i, data=data, publish_time=i)
        w.finish()
    return path


@pytest.mark.parametrize(
    "payloads", [[json.dumps({"t": i}).encode() for i in range(3)], [b"\x00\xff garbage"] * 3]
)
@pytest.mark.parametrize("command", ["info", "report"])
def test_a_log_without_one_readable_cycle_is_refused(tmp_path, capsys, payloads, command):
    log = _log_of_bad_cycles(tmp_path / "bad.mcap", payloads)
    assert main([command, str(log)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        f"hil {command}: error: {log}: not a hil log: none of its 3 {CYCLE} record(s) is "
        "readable and it has no hil.config or hil.run metadata"
    )


@pytest.mark.parametrize(
    "args",
    [
        ["recover", "LOG", "--out", ""],
        ["replay", "LOG", "--out", ""],
        ["export", "LOG", "--format", "csv", "--out", ""],
        ["sweep", "SPEC", "--out", ""],
        ["experiment", "fig3", "--out", ""],
        ["report", "LOG", "--plot", ""],
        ["param", "dump", "--out", ""],
        ["controller", "--log", ""],
        ["up", "--log", ""],
        ["camera", "calibrate", "--source", "emulated", "--write", ""],
    ],
)
def test_an_empty_output_path_is_refused(args, capsys):
    with pytest.raises(SystemExit) as stop:
        main(args)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    option = args[args.index("") - 1]
    assert err.endswith(f"{option}: the path is empty") and ": error: argument " in err, err
