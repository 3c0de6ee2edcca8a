"""``hil experiment --set KEY=VALUE``: keys changed for every run of the experiment; the keys
the experiment itself varies, or another option sets, are refused before anything is written."""

from __future__ import annotations

import pytest

from hal.config import load_config
from rt_controller.rig import experiment as ex
from rt_controller.rig.experiment_markdown import render_report
from rt_controller.rig.experiment_results import build_results
from tests.support import error_line


def test_every_run_s_config_has_the_set_keys_and_the_results_name_them(tmp_path):
    sets = {"camera.model": "analytic", "gains.kp": 0.3, "rates.control_hz": 100.0}
    s = ex.Settings(experiments=("fig3", "table1"), out=tmp_path, reps=1, sets=sets)
    plan, runs = ex.prepare(s)
    assert len(runs) == 6
    for run in runs.values():
        cfg = load_config(run.config_file)
        assert (cfg.camera.model, cfg.gains.kp, cfg.rates.control_hz) == ("analytic", 0.3, 100.0)
    # the runs' own keys still come from the plan (table1 on the analytic camera: 0.5 px)
    table1 = [r for r in runs.values() if r.spec.rep is not None]
    assert [r.config.camera.noise_px for r in table1] == [ex.TABLE1_DEFAULT_NOISE_PX] * 3
    assert s.hardware_profile() == "dsp" and s.base_config().gains.kp == 0.3
    results = build_results(s, plan, runs, "hil experiment ...")
    assert (results["config_sets"], results["camera_model"], results["rate_hz"]) == (
        sets,
        "analytic",
        100.0,
    )
    report = render_report(results)
    assert 'with `--set camera.model="analytic"` `--set gains.kp=0.3`' in report


@pytest.mark.parametrize(
    ("key", "why"),
    [
        ("controller.law", "each experiment sets the law of its runs"),
        ("rhc.horizon", "each experiment sets the horizon of its runs"),
        ("camera.noise_px", "use --noise"),
        ("controller.clock", "lockstep, or --realtime"),
        ("hardware.profile", "use --profile"),
        ("transport.can", "the runs' transports come from --can and the --config file"),
    ],
)
def test_a_set_of_what_the_experiment_decides_is_refused_before_anything_is_written(
    tmp_path, capsys, key, why
):
    out = tmp_path / "exp"
    err = error_line(["experiment", "fig3", "--set", f"{key}=1", "--out", str(out)], capsys)
    assert err == f"hil experiment: error: --set {key}: {why}"
    assert not out.exists()


def test_a_bad_set_value_is_refused_naming_the_key(tmp_path, capsys):
    argv = ["experiment", "fig3", "--set", "camera.model=bogus", "--out", str(tmp_path / "x")]
    assert "camera.model (--set): must be image or analytic" in error_line(argv, capsys)
