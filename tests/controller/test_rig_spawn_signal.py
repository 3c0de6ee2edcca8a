"""A stop signal that lands while ``Rig.spawn`` starts a child: the child is the rig's all the
same, so the stop reaches it with SIGTERM (its orderly stop) and its exit is in the summary.

Before, the signal raised out of ``subprocess.Popen`` after the fork: the child ran on unknown
to the rig, got no SIGTERM and was SIGKILLed with the group 10 s later (a controller's log
left unfinished, and no exit code for it in ``hil up``'s summary).
"""

from __future__ import annotations

import signal
import subprocess
import sys

import pytest

from rt_controller.rig.options import RigOptions
from rt_controller.rig.processes import Rig
from rt_controller.rig.supervise import RigInterrupted, supervised


def test_a_signal_during_spawn_leaves_the_child_to_the_rig(monkeypatch):
    real_popen = subprocess.Popen

    def popen_hit_by_a_hangup(*args, **kwargs):
        proc = real_popen(*args, **kwargs)  # the fork is done: the child runs
        signal.raise_signal(signal.SIGHUP)  # as if it landed before Popen returned
        return proc

    monkeypatch.setattr(subprocess, "Popen", popen_hit_by_a_hangup)
    sleeper = [sys.executable, "-c", "import time; time.sleep(60)"]
    with Rig(RigOptions(lockstep=True)) as rig:
        with pytest.raises(RigInterrupted), supervised():
            rig.spawn("controller", sleeper)
        child = rig.child("controller")
        assert child is not None, "the started child is not the rig's"
        codes = rig.stop()
    assert codes == {"controller": -signal.SIGTERM}
