"""The rig runs without SciPy (a test-only dependency): numba links its linear algebra (``@`` on
arrays, ``np.dot``) to SciPy's BLAS, and a compiled kernel that uses it without SciPy installed
kills the process with "Fatal Python error: BLAS wrapper returned with an error". Each check
runs in a child process in which ``import scipy`` fails, as on a machine without it."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from tests.support import REPO

NO_SCIPY = "import sys\nsys.modules['scipy'] = None  # as if SciPy were not installed\n"


def _run(code: str) -> subprocess.CompletedProcess[str]:
    src = NO_SCIPY + textwrap.dedent(code)
    return subprocess.run(
        [sys.executable, "-c", src], cwd=REPO, capture_output=True, text=True, timeout=300
    )


@pytest.mark.parametrize(
    "what, code",
    [
        (
            "emulator physics",
            """
            import numpy as np
            from hal.config import load_config
            from plant_emulator.arm import ArmPhysics
            from plant_emulator.world import World
            cfg = load_config()
            arm = ArmPhysics(cfg.robot)
            m = arm.inertia(np.array([0.3, -0.4]))
            assert m.shape == (2, 2) and abs(m[0, 1] - m[1, 0]) < 1e-15
            world = World(cfg)
            q0 = world.q.copy()
            world.hold(np.array([1.0, 0.2]), 20)
            assert np.all(np.isfinite(world.q)) and not np.array_equal(world.q, q0)
            print("ok")
            """,
        ),
        (
            "controller laws",
            """
            from hal.config import load_config
            from rt_controller.control.controller import Controller
            cfg = load_config()
            for law in ("pbc", "ioc", "rhc"):
                Controller(cfg, law).warm_up()
            print("ok")
            """,
        ),
    ],
)
def test_runs_where_scipy_cannot_be_imported(what: str, code: str) -> None:
    res = _run(code)
    assert res.returncode == 0 and res.stdout.strip() == "ok", (what, res.stderr[-2000:])
