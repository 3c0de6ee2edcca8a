"""``hil emulator`` options that do nothing for the profile being emulated are refused (exit 2,
one line) instead of being silently ignored."""

from __future__ import annotations

from pathlib import Path

from hal.bus import isolated_spec
from tests.support import run_hil


def test_state_rate_with_the_cia402_profile_is_refused(tmp_path: Path) -> None:
    key = tmp_path / "rig.key"
    assert run_hil(["keygen", str(key)], timeout_s=60).returncode == 0
    args = ["emulator", "--profile", "cia402", "--state-rate", "100", "--no-vision-link"]
    args += ["--can", isolated_spec("udp_multicast"), "--key-file", str(key), "--duration", "0.1"]
    done = run_hil(args, timeout_s=120)
    assert done.returncode == 2, (done.returncode, done.stderr)
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("hil emulator: error: --state-rate"), lines
    assert "Traceback" not in done.stderr
