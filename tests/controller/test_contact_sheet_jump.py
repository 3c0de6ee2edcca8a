"""hil report --plot's contact sheet is of the target jump: none for a run without a jump
(scenario.disturbance = false) or one that ended before it (a short or stopped run), rather
than a sheet titled "around the target jump" of frames that are all before it."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from hal.config import RigConfig
from hal.vision_image import VisionImage, encode_vision_image
from rt_controller.logtools.contact_sheet import frames_around, write_contact_sheet
from rt_controller.logtools.reader import read_log
from rt_controller.runtime.recorder import IMAGE, CycleRecorder

PERIOD_NS = 20_000_000


def _log(tmp_path, ticks: int, cfg: RigConfig | None = None):
    path = tmp_path / "run.mcap"
    rec = CycleRecorder(path, cfg or RigConfig())
    t0 = 10**9
    for k in range(ticks):  # 50 Hz, frames at 10 fps
        rec.record_cycle({"tick": k, "t_ns": t0 + k * PERIOD_NS, "sim_time_s": k * 0.02})
        if k % 5 == 0:
            pixels = np.full((48, 64), 200, np.uint8)
            cv2.circle(pixels, (10 + k // 5, 24), 4, 40, -1)
            _, png = cv2.imencode(".png", pixels)
            msg = VisionImage(
                k // 5, t0 + k * PERIOD_NS, k * PERIOD_NS, True, None,
                (10.0, 24.0), (1.0, 2.0), png.tobytes(),
            )  # fmt: skip
            rec.write(IMAGE, 0, encode_vision_image(msg))
    rec.close()
    return read_log(path)


def test_a_run_that_ended_before_the_jump_has_no_sheet(tmp_path):
    log = _log(tmp_path, ticks=100)  # 2 s, the jump at 3 s
    assert frames_around(log, 3.0) == []
    assert not write_contact_sheet(log, tmp_path / "sheet.png")
    assert not (tmp_path / "sheet.png").exists()


def test_a_run_of_a_few_ticks_has_no_sheet(tmp_path):
    log = _log(tmp_path, ticks=3)
    assert not write_contact_sheet(log, tmp_path / "sheet.png")


def test_a_run_without_a_jump_has_no_sheet(tmp_path):
    base = RigConfig()
    cfg = replace(base, scenario=replace(base.scenario, disturbance=False))
    log = _log(tmp_path, ticks=200, cfg=cfg)
    assert log.config is not None and not log.config.scenario.disturbance
    assert not write_contact_sheet(log, tmp_path / "sheet.png")


def test_a_run_that_reached_the_jump_has_its_sheet(tmp_path):
    log = _log(tmp_path, ticks=160)  # to 3.18 s: frames on both sides of 3 s
    frames = frames_around(log, 3.0)
    assert [round(f["t_s"], 2) for f in frames] == [2.6, 2.7, 2.8, 2.9, 3.0, 3.1]
    assert write_contact_sheet(log, tmp_path / "sheet.png")
