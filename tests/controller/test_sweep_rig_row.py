"""A rig run's row in a sweep, from the controller's JSON summary: a figure the summary has
no value for (``null``: a run that never ran the law has no final features) is NaN in the
row, not a crash that turns a finished run into a failed one."""

from __future__ import annotations

import math

from hal.config import load_config
from rt_controller.runtime.recorder import CycleRecorder
from rt_controller.sweep import engines
from rt_controller.sweep.spec import RunTask


def test_a_summary_without_final_features_gives_a_nan_figure(tmp_path, monkeypatch):
    cfg = load_config()
    task = RunTask(
        key="k1", point=0, rep=0, seed=1, axes={}, config=cfg.to_dict(), engine="rig",
        duration_s=1.0, timeout_s=60.0, spec_hash="h", log_dir=str(tmp_path),
    )  # fmt: skip

    def run_rig(opts):  # the controller stopped before arming, as its --json line says
        with CycleRecorder(opts.log, cfg, run_info={"law": "ioc"}):
            pass
        return {"J": 0.0, "f_final_norm": None, "ticks": 0, "dsp_faults": {}}

    monkeypatch.setattr("rt_controller.rig.processes.run_rig", run_rig)
    row = engines.rig_run(task)
    assert row["J"] == 0.0 and math.isnan(row["f_final_norm"]) and row["ticks"] == 0
