"""``run.can_frames`` keeps integer DBC signals integers: a signal that some frames lack is a
pandas nullable integer column (``Int64``, ``<NA>`` where absent), not float64 with NaN;
scaled and float signals stay float64. The log is written through the recorder's public seam
(:class:`CycleRecorder`) with frames encoded by the rig's codecs."""

from __future__ import annotations

import pytest

from rt_controller.logs import load
from tests.support.can_log import TICKS, write_tick_log

pd = pytest.importorskip("pandas")


@pytest.fixture
def frames(tmp_path):
    return load(write_tick_log(tmp_path / "run.mcap")).can_frames


def test_an_integer_signal_absent_from_some_frames_is_a_nullable_integer(frames):
    assert list(frames["message"]) == ["Sync", "JointPosition"] * len(TICKS)
    assert frames["Tick"].dtype == "Int64"
    sync = frames["message"] == "Sync"
    assert list(frames.loc[sync, "Tick"]) == list(TICKS)  # exact, as integers
    assert frames.loc[~sync, "Tick"].isna().all()
    for name in ("Counter", "Sample", "Freshness", "Mac", "CRC"):
        assert frames[name].dtype == "Int64", name


def test_scaled_signals_stay_float(frames):
    assert frames["Q1"].dtype == "float64"
    position = frames["message"] == "JointPosition"
    assert frames.loc[position, "Q1"].tolist() == pytest.approx([0.25] * len(TICKS), abs=1e-5)
    assert frames.loc[~position, "Q1"].isna().all()
