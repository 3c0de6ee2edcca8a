"""A first run after install behaves like every later run: once a process on the tick path has
warmed up (before the DSP is armed), its loop compiles and loads nothing.

Each check runs in a fresh interpreter with an empty numba cache, because within this test
process other tests have already compiled everything. numba reports every compilation (and every
load from its cache) as a ``numba:compile`` event; a warmed-up loop must emit none.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

CONTROLLER_LOOP = """
import json, sys
import numpy as np
from numba.core import event
from hal.config import load_config
from rt_controller.control.controller import Controller

cfg = load_config().with_overrides({"controller.law": sys.argv[1]})
ctl = Controller(cfg)
ctl.warm_up()
rng = np.random.default_rng(0)
q0, f0 = np.array(cfg.scenario.q0), np.array(cfg.scenario.f0)
with event.install_recorder("numba:compile") as rec:
    for k in range(60):
        q = q0 + rng.normal(0, 0.05, 2)
        dq = rng.normal(0, 0.2, 2)
        f = f0 * (1 - k / 60) + rng.normal(0, 1, 2)
        d = ctl.decide(k * 0.02, q, dq, f, f_stale=k % 17 == 5, state_stale=k % 23 == 7)
        d.record_fields(ctl.law)
print(json.dumps([str(ev.data.get("dispatcher", ev)) for _, ev in rec.buffer]))
"""

DSP_LOOP = """
import json, sys, threading
import numpy as np
from numba.core import event
from hal.bus import isolated_spec, open_bus
from hal.config import load_config
from plant_emulator.dsp import make_dsp

cfg = load_config()
lockstep = sys.argv[1] == "lockstep"
with open_bus(isolated_spec("virtual")) as bus:
    node = make_dsp(cfg, bus, lockstep=lockstep)
    node.warm_up()
    with event.install_recorder("numba:compile") as rec:
        if lockstep:
            for _ in range(20):
                node.advance_period()
        else:
            node.start_realtime(0)
            node.service(200 * node.physics_period_ns)
print(json.dumps([str(ev.data.get("dispatcher", ev)) for _, ev in rec.buffer]))
"""


def _compiles_after_warm_up(script: str, arg: str, tmp_path) -> list[str]:
    env_cache = tmp_path / "numba-cache"
    proc = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script), arg],
        capture_output=True,
        text=True,
        timeout=600,
        env={**__import__("os").environ, "NUMBA_CACHE_DIR": str(env_cache)},
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.slow
@pytest.mark.parametrize("law", ["pbc", "ioc", "rhc"])
def test_controller_tick_compiles_nothing_after_warm_up(law, tmp_path):
    assert _compiles_after_warm_up(CONTROLLER_LOOP, law, tmp_path) == []


@pytest.mark.slow
@pytest.mark.parametrize("clock", ["realtime", "lockstep"])
def test_dsp_physics_compiles_nothing_after_warm_up(clock, tmp_path):
    assert _compiles_after_warm_up(DSP_LOOP, clock, tmp_path) == []
