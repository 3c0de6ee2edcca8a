"""The rig's numba kernels compiled once, before its processes start.

On a cold cache (a fresh install, a new checkout, a changed kernel) the controller compiles its
rule and the emulator its arm model as they start, for a minute or more on a busy 2-core host.
That time belongs to neither the run nor its wall-clock budget: a run that spends it compiling
would be called hung. So a rig first runs one tick of ``hil simulate`` (the controller's rule
and the emulator's arm physics, the kernels the children load), once per process and rig
configuration; with a warm cache that costs about 2 s, and the children then load what it wrote.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time

from rt_controller.rig.failures import RigCancelled

_prepared: set[tuple[str | None, str | None]] = set()
_lock = threading.Lock()


def prepare_kernels(
    config: str | None, law: str | None, cancel: threading.Event | None = None
) -> bool:
    """Compile (or load) the kernels a rig of ``config`` and ``law`` runs, once per process;
    whether this call ran the compile step. A failing step is left to the children to report
    with their own error line (a bad config is their usage error, not this one's)."""
    key = (config, law)
    with _lock:
        if key in _prepared:
            return False
        argv = [sys.executable, "-m", "rt_controller.cli", "simulate", "--duration", "0.02", "-q"]
        if config:
            argv += ["--config", config]
        if law:
            argv += ["--law", law]
        proc = subprocess.Popen(
            argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        try:
            while proc.poll() is None:
                if cancel is not None and cancel.is_set():
                    raise RigCancelled("cancelled")
                time.sleep(0.05)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        if proc.returncode == 0:
            _prepared.add(key)
        return True
