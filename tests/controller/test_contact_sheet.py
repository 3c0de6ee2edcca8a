"""hil report --plot's contact sheet: the logged camera frames nearest the target jump, on the
simulation time axis of the cycles, with the detector's verdict; none for a log without frames."""

from __future__ import annotations

import cv2
import numpy as np

from hal.config import RigConfig
from hal.vision_image import VisionImage, encode_vision_image
from rt_controller.logtools.contact_sheet import frames_around, write_contact_sheet
from rt_controller.logtools.reader import read_log
from rt_controller.runtime.recorder import IMAGE, CycleRecorder

PERIOD_NS = 20_000_000


def _log(tmp_path, *, images: bool):
    path = tmp_path / "run.mcap"
    rec = CycleRecorder(path, RigConfig())
    t0 = 10**9
    for k in range(200):  # 4 s at 50 Hz, the jump at 3 s
        rec.record_cycle({"tick": k, "t_ns": t0 + k * PERIOD_NS, "sim_time_s": k * 0.02})
        if images and k % 5 == 0:  # 10 fps
            pixels = np.full((48, 64), 200, np.uint8)
            cv2.circle(pixels, (10 + k // 5, 24), 4, 40, -1)
            _, png = cv2.imencode(".png", pixels)
            valid = k != 150
            msg = VisionImage(
                k // 5, t0 + k * PERIOD_NS, k * PERIOD_NS, valid, None if valid else "blurred",
                (10.0 + k // 5, 24.0) if valid else (0.0, 0.0), (1.0, 2.0), png.tobytes(),
            )  # fmt: skip
            rec.write(IMAGE, 0, encode_vision_image(msg))
    rec.close()
    return read_log(path)


def test_the_frames_around_the_jump_with_their_verdicts(tmp_path):
    log = _log(tmp_path, images=True)
    frames = frames_around(log, 3.0)
    assert [round(f["t_s"], 3) for f in frames] == [2.6, 2.7, 2.8, 2.9, 3.0, 3.1, 3.2, 3.3]
    assert frames[4]["label"] == "no target: blurred"
    assert frames[0]["label"] == "detected f = (1.00, 2.00) px"
    assert frames[0]["pixels"].shape == (48, 64)
    assert write_contact_sheet(log, tmp_path / "sheet.png")
    assert (tmp_path / "sheet.png").stat().st_size > 0


def test_no_sheet_without_frames(tmp_path):
    log = _log(tmp_path, images=False)
    assert frames_around(log, 3.0) == []
    assert not write_contact_sheet(log, tmp_path / "sheet.png")


def test_a_log_whose_writer_was_killed_still_gives_its_frames(tmp_path):
    """No footer or summary (the recorder killed): the frames are read as far as the file goes,
    like the rest of the log, not with mcap's seeking reader (which raised)."""
    log = _log(tmp_path, images=True)
    data = log.path.read_bytes()
    log.path.write_bytes(data[:-30])  # the footer and the end of the summary cut off
    cut = read_log(log.path)
    assert cut.truncated
    assert len(frames_around(cut, 3.0)) == 8
    assert write_contact_sheet(cut, tmp_path / "sheet.png")


def test_a_non_integer_clock_offset_gives_no_sheet(tmp_path):
    log = _log(tmp_path, images=True)
    log.run_info["monotonic_to_unix_ns"] = "abc"
    assert frames_around(log, 3.0) == []
