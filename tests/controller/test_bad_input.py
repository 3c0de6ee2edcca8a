"""Every bad input of the safety review gets one clear line and status 2: no traceback, no hang
(each case runs the real ``hil`` under a timeout), nothing started or waited for first."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from hal.zenoh_session import free_loopback_port

HIL = [sys.executable, "-m", "rt_controller.cli"]
TIMEOUT_S = 60.0
"""A hang fails the case; a correct refusal takes well under a second."""


def _toml(tmp_path: Path, text: str | bytes) -> str:
    path = tmp_path / "bad.toml"
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    return str(path)


def _log_with_config(tmp_path: Path, key: str, value: object) -> str:
    """A small valid log whose embedded configuration is then given a bad value."""
    import json

    from hal.config import load_config
    from rt_controller.runtime.recorder import CONFIG_METADATA, CycleRecorder

    cfg = load_config()
    path = tmp_path / "bad-config.mcap"
    with CycleRecorder(path, cfg) as rec:
        rec.record_cycle({"tick": 0, "t_ns": 1, "u": [0.0, 0.0], "tau": [0.0, 0.0]})
    # Re-write the file with the config metadata changed: read it back, patch, write anew.
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with path.open("rb") as fh:
        reader = make_reader(fh)
        metadata = list(reader.iter_metadata())
        messages = list(reader.iter_messages())
    out = tmp_path / "patched.mcap"
    with out.open("wb") as fh:
        w = Writer(fh)
        w.start()
        for md in metadata:
            data = dict(md.metadata)
            if md.name == CONFIG_METADATA:
                doc = json.loads(data["json"])
                section, name = key.split(".")
                doc[section][name] = value
                data["json"] = json.dumps(doc)
            w.add_metadata(md.name, data)
        ids: dict[int, int] = {}
        for schema, channel, message in messages:
            if channel.id not in ids:
                sid = w.register_schema(schema.name, schema.encoding, schema.data)
                ids[channel.id] = w.register_channel(channel.topic, channel.message_encoding, sid)
            w.add_message(ids[channel.id], message.log_time, message.data, message.publish_time)
        w.finish()
    return str(out)


def simulate_with(text: str | bytes):
    """The case: ``hil simulate`` with a config file holding ``text``."""
    return lambda t: ["simulate", "--config", _toml(t, text)]


CASES = {
    "non-UTF-8 config file": simulate_with(b"[rhc]\nsteps = \xff\n"),
    "control rate 1e-9 Hz": lambda t: ["simulate", "--rate", "1e-9"],
    "20 million horizon steps": lambda t: ["simulate", "--law", "rhc", "--steps", "20000000"],
    "horizon 1e6 s": lambda t: ["simulate", "--law", "rhc", "--horizon", "1e6"],
    "rhc.steps = 1e9 in a file": simulate_with("[rhc]\nsteps = 1000000000\n"),
    "physics_hz = 1e300": simulate_with("[rates]\nphysics_hz = 1e300\n"),
    "watchdog of 1e12 periods": simulate_with("[dsp]\nwatchdog_periods = 1e12\n"),
    "feature timeout 1e12 s": simulate_with("[controller]\nfeature_timeout_s = 1e12\n"),
    "NaN gain": simulate_with("[gains]\nkp = nan\n"),
    "hil up --duration nan": lambda t: ["up", "--duration", "nan"],
    "hil up --duration inf": lambda t: ["up", "--duration", "inf"],
    "hil controller --duration -5": lambda t: ["controller", "--duration", "-5"],
    "hil simulate --duration 0": lambda t: ["simulate", "--duration", "0"],
    "hil emulator --duration nan": lambda t: ["emulator", "--duration", "nan"],
    "hil vision --fps -1": lambda t: ["vision", "--fps", "-1"],
    "hil experiment --reps 0": lambda t: ["experiment", "table1", "--reps", "0"],
    "rhc.steps = 1e9 inside a log": lambda t: ["replay", _log_with_config(t, "rhc.steps", 10**9)],
    "a bad --can, before any zenoh wait": lambda t: [
        "controller",
        "--can",
        "nosuchbus:x",
        "--zenoh-endpoint",
        f"tcp/127.0.0.1:{free_loopback_port()}",
        "--duration",
        "1",
    ],
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input_gets_one_clear_line_and_status_2(case, tmp_path):
    argv = CASES[case](tmp_path)
    done = subprocess.run([*HIL, *argv], capture_output=True, text=True, timeout=TIMEOUT_S)
    err = done.stderr.strip()
    assert done.returncode == 2, (done.returncode, err)
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if not ln.startswith("usage:") and ln.strip()]
    # argparse prints its usage first, then one line; our own errors are one line
    errors = [ln for ln in lines if "error:" in ln]
    assert len(errors) == 1 and errors[0].startswith("hil"), err
