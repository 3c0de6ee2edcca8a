"""``hal.lean_start``: the rig's daemons start without SciPy's linear algebra."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

from hal.bus import isolated_spec
from tests.support import REPO


def _child(code: str) -> str:
    res = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode == 0, res.stderr[-2000:]
    return res.stdout.strip()


def test_scipy_linalg_is_not_imported_and_the_kernels_still_run():
    out = _child(
        """
        import sys
        from hal.lean_start import without_scipy_linalg
        assert without_scipy_linalg()
        try:
            import scipy.linalg  # noqa: F401
        except ImportError:
            pass
        else:
            raise SystemExit("scipy.linalg imported")
        import numpy as np
        from hal.config import load_config
        from plant_emulator.world import World
        World(load_config()).hold(np.ones(2), 3)
        print(sys.modules.get("scipy.linalg") is None)
        """
    )
    assert out == "True"


def test_an_already_imported_scipy_linalg_is_left_alone():
    out = _child(
        """
        import importlib.util
        if importlib.util.find_spec("scipy") is None:
            print("no scipy")
        else:
            import scipy.linalg
            from hal.lean_start import without_scipy_linalg
            print(without_scipy_linalg(), scipy.linalg.__name__)
        """
    )
    assert out in ("False scipy.linalg", "no scipy")


def test_the_emulator_daemon_runs_its_kernels_without_loading_scipy_linalg(tmp_path):
    """``hil emulator`` after its warm-up (numba kernels loaded, "serving the arm" printed):
    no SciPy linear-algebra library is mapped into the process."""
    import os
    import signal
    import time

    err = tmp_path / "emulator.err"
    with err.open("wb") as fh:
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "rt_controller.cli",
                "emulator",
                "--lockstep",
                "--can",
                isolated_spec("udp_multicast"),  # a bus of its own: no peer is needed
            ],
            cwd=REPO,
            stdout=subprocess.DEVNULL,
            stderr=fh,
            env={**os.environ, "HIL_KEY_FILE": str(_key(tmp_path))},
        )
    try:
        deadline = time.monotonic() + 120
        while b"serving the arm" not in err.read_bytes():
            assert proc.poll() is None, err.read_text()
            if time.monotonic() > deadline:
                raise AssertionError(f"the emulator did not start: {err.read_text()}")
            time.sleep(0.05)
        maps = Path(f"/proc/{proc.pid}/maps").read_text()
        assert "llvmlite" in maps  # numba is loaded
        assert "scipy/linalg" not in maps
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(30)


def _key(tmp_path):
    from hal.secoc import write_key_file

    return write_key_file(tmp_path / "rig.key")
