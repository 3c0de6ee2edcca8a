"""``hil bench vision``'s rig sections: a lockstep rig with images profiled period by period
(its J is the plain lockstep rig's, bit for bit: same seed, and so is the run's without the
image log), a clean camera's lockstep J against the analytic camera's, and the pipeline timed
while a realtime rig runs at 60 fps. Times are reported, never asserted."""

from __future__ import annotations

import json

import pytest

from tests.support import run_hil

pytestmark = pytest.mark.integration


def test_rig_sections_report_the_pipeline_while_rigs_run():
    proc = run_hil(
        [
            "bench",
            "vision",
            "--json",
            "-q",
            "--grid",
            "2",
            "--latency-frames",
            "0",
            "--lockstep-duration",
            "1",
            "--realtime-duration",
            "3",
        ],
        timeout_s=600,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)
    prof = out["lockstep_profile"]
    assert prof["ticks"] == 50 and prof["J"] == out["lockstep"]["image"]["J"]
    # logging what the camera saw does not touch the loop: the same J without the image log
    assert out["lockstep"]["image_no_log"]["J"] == out["lockstep"]["image"]["J"]
    # noise, blur and lens off: the analytic camera's J to 0.5 % (+0.010 % over this 1 s)
    clean = out["lockstep"]["image_clean"]
    assert clean["ticks"] == 50 and abs(clean["J_vs_analytic"]) <= 0.005
    for key in ("pose_to_frame_us", "frame_to_features_us", "detect_us"):
        assert 0 < prof[key]["median"] <= prof[key]["p99"]
    assert prof["image_log"]["sent"] >= 10 and prof["image_log"]["dropped"] == 0
    rt = out["realtime"]
    assert rt["fps"] == 60.0 and rt["frames_measured"] > 60
    assert 0 < rt["pipeline_us"]["median"] <= rt["pipeline_us"]["p99"]
    assert rt["frames_rendered"] >= rt["frames_measured"]
    assert isinstance(rt["deadline_misses"], int)
