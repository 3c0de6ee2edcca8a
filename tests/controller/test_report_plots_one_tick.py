"""hil report --plot of a log of one tick (a run stopped at once, or --duration of one period):
its figures show that tick (a marker), not empty axes (a line of one point draws nothing)."""

from __future__ import annotations

import numpy as np
from matplotlib.image import imread

from hal.config import RigConfig
from rt_controller.logtools.reader import read_log
from rt_controller.logtools.report_plots import write_plots
from rt_controller.runtime.recorder import CycleRecorder

BLUE = np.array([0x1F, 0x77, 0xB4]) / 255  # matplotlib's tab:blue, the first line's colour


def _blue_pixels(png) -> int:
    rgb = imread(png)[..., :3]
    return int(np.sum(np.all(np.abs(rgb - BLUE) < 0.03, axis=-1)))


def _log(tmp_path, ticks: int):
    path = tmp_path / "run.mcap"
    rec = CycleRecorder(path, RigConfig())
    for k in range(ticks):
        rec.record_cycle(
            {"tick": k, "t_ns": 10**9 + k * 20_000_000, "sim_time_s": k * 0.02,
             "solve_us": 50.0 + k, "residual": 0.0, "cycle_us": 300.0, "lateness_us": 1.0}
        )  # fmt: skip
    rec.close()
    return read_log(path)


def test_the_solve_time_of_a_one_tick_log_is_drawn(tmp_path):
    written = write_plots(_log(tmp_path, 1), tmp_path / "figs")
    solve = tmp_path / "figs" / "run_solve_time.png"
    assert solve in written
    assert _blue_pixels(solve) > 0  # the one solve time (no legend entry is blue here)


def test_the_solve_time_of_a_longer_log_is_drawn_too(tmp_path):
    write_plots(_log(tmp_path, 20), tmp_path / "figs")
    assert _blue_pixels(tmp_path / "figs" / "run_solve_time.png") > 0
