"""The live service (``hil up``: emulator, vision and controller as separate processes) as the
live tests run it: ``tests/integration/test_live_lockstep.py``, ``test_live_sigkill.py``,
``test_live_stale_inputs.py`` and ``test_live_rig_reporting.py``.

Every run gets its own CAN port (:func:`hal.bus.isolated_spec`) and zenoh port
(:func:`rig_options`), so parallel runs and other rigs on the host never meet.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from hal.bus import isolated_spec
from hal.config import load_config
from rt_controller.logtools.reader import read_log
from rt_controller.rig.options import RigOptions
from rt_controller.rig.processes import Rig
from tests.support import free_endpoint

CFG = load_config()
PERIOD_S = CFG.rates.control_period_ns / 1e9
RATE_HZ = CFG.rates.control_hz


def rig_options(log: Path, **kw: Any) -> RigOptions:
    """A rig on its own CAN port and zenoh port, logging to ``log``."""
    kw.setdefault("can", isolated_spec("udp_multicast"))
    kw.setdefault("zenoh_endpoint", free_endpoint())
    # a busy host can take longer than vision's default 10 s to bring the emulator's hub up
    kw["extra_vision"] = ["--wait", "120", *kw.get("extra_vision", [])]
    return RigOptions(log=log, **kw)


def norm(f: np.ndarray) -> np.ndarray:
    """|f| of each feature error ``f`` (rows of (x, y) px)."""
    return np.hypot(f[:, 0], f[:, 1])


def wait_for_cycles(log: Path, n: int, rig: Rig, timeout_s: float = 120.0) -> dict[str, np.ndarray]:
    """Poll the growing log until it holds ``n`` cycles (a generous timeout: a busy host delays
    start-up and the writer); the cycles read at that moment."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for c in rig.children:
            assert c.proc.poll() is None, f"{c.name} exited early:\n{c.tail()}"
        if log.exists() and log.stat().st_size > 0:
            cycles = read_log(log, raw=False).cycles
            if len(cycles.get("tick", ())) >= n:
                return cycles
        time.sleep(0.1)
    raise AssertionError(f"the controller logged fewer than {n} cycles in {timeout_s} s")
