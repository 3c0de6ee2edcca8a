"""``hil experiment``'s report describes the hardware profile of its runs: every profile the
configuration accepts (``hal.config.PROFILES``) has its words, in lockstep and realtime, so a
new profile without them is caught here, not by a KeyError after an hour of runs."""

from __future__ import annotations

import pytest

from hal.config import PROFILES
from hal.strict_json import finite
from rt_controller.rig import experiment as ex
from rt_controller.rig.experiment_markdown import render_report
from rt_controller.rig.experiment_results import build_results


@pytest.mark.parametrize("realtime", [False, True], ids=["lockstep", "realtime"])
@pytest.mark.parametrize("profile", PROFILES)
def test_every_profile_has_its_words_in_the_report(tmp_path, profile, realtime):
    settings = ex.Settings(
        experiments=("fig4",), out=tmp_path, reps=1, profile=profile, realtime=realtime
    )
    runs_by_exp, runs = ex.prepare(settings)
    for i, run in enumerate(runs.values()):
        run.status, run.summary, run.J_steady = "ok", {"J": 10.0 + i}, 1.0 + i
    report = render_report(finite(build_results(settings, runs_by_exp, runs, "hil experiment")))
    assert f"- Hardware profile: **{profile}** (" in report, report
