"""``hil vision`` stopped (SIGTERM/SIGINT) while it still waits for the zenoh hub says so on
stderr (exit 0) instead of ending without a word: nothing was measured, and a ``--json``
reader gets no counters."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from tests.support import free_endpoint, run_hil, start_hil

pytestmark = pytest.mark.integration

ANALYTIC = '[camera]\nmodel = "analytic"\n'


@pytest.mark.parametrize("model", ["analytic", "image"])
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_stop_while_waiting_for_the_hub_is_told(tmp_path: Path, model: str, sig) -> None:
    key = tmp_path / "rig.key"
    assert run_hil(["keygen", str(key)], timeout_s=60).returncode == 0
    args = ["vision", "--key-file", str(key), "--zenoh-endpoint", free_endpoint(), "--wait", "600"]
    if model == "analytic":
        (tmp_path / "rig.toml").write_text(ANALYTIC)
        args += ["--config", str(tmp_path / "rig.toml")]
    proc = start_hil(args, capture=True)
    try:
        banner = proc.stderr.readline()  # printed once the stop handlers are installed
        assert banner.startswith("hil vision: "), banner
        proc.send_signal(sig)
        _out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:  # pragma: no cover - only on a hang
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 0, (proc.returncode, err)
    assert "Traceback" not in err
    assert f"stopped by {sig.name} while waiting for the zenoh hub" in err, err
