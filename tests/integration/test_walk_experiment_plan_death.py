"""``hil experiment``'s lockstep batches run as a plan on one set of processes: when a shared
process (the emulator, vision) dies in a run, the run it cut short failed, and the runs after
it are not run (they never started), saying which process died in which run; they are not
failures of their own."""

from __future__ import annotations

import pytest

from rt_controller.rig.experiment import Settings, execute_batch, prepare
from tests.support import killed_once_ticking

pytestmark = pytest.mark.integration

TICKS_BEFORE_KILL = 50


@pytest.mark.parametrize("victim", ["emulator", "vision"])
def test_runs_after_a_shared_process_died_are_not_run(tmp_path, victim):
    settings = Settings(experiments=("fig3",), out=tmp_path / "exp", duration_s=600.0, jobs=1)
    _, runs = prepare(settings)
    batch = list(runs.values())
    first = batch[0]
    with killed_once_ticking(first.log, victim, TICKS_BEFORE_KILL):
        execute_batch(batch, settings)
    assert first.status == "failed" and victim in (first.error or ""), first.error
    for run in batch[1:]:
        assert run.status == "pending", (run.spec.name, run.status, run.error)
        said = f"not run: the {victim} ended in run {first.spec.name} (killed by SIGKILL)"
        assert run.error == said
        assert run.J is None
