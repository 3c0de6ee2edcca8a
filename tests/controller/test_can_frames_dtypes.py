"""``run.can_frames`` keeps integer DBC signals integers: a signal that some frames lack is a
pandas nullable integer column (``Int64``, ``<NA>`` where absent), not float64 with NaN;
scaled and float signals stay float64. The log is written through the recorder's public seam
(:class:`CycleRecorder`) with frames encoded by the rig's codecs."""

from __future__ import annotations

import pytest

from hal.can_codec import DspCodec
from hal.config import RigConfig
from rt_controller.logs import load
from rt_controller.runtime.recorder import CycleRecorder

pd = pytest.importorskip("pandas")

T0_NS = 1_000_000_000
TICKS = (4_294_967_295, 4_294_967_294, 123_456_789)  # the widest integer signal: 32 bits


@pytest.fixture
def frames(tmp_path):
    """Sync frames (``Tick``, ``Counter``) between JointPosition frames (``Q1``, ``Q2`` and
    ``Sample``, no ``Tick``): ``Tick`` is present in some rows and absent in the others."""
    path = tmp_path / "run.mcap"
    dsp = DspCodec()
    info = {"clock": "lockstep", "can": "virtual", "zenoh": "tcp/127.0.0.1:1", "recorder": "thread"}
    with CycleRecorder(path, RigConfig(), run_info=info) as rec:
        for i, tick in enumerate(TICKS):
            rec.record_can(dsp.encode_sync(tick), T0_NS + 2 * i * 1000, "rx")
            position, _ = dsp.encode_state((0.25, -0.5), (0.0, 0.0), i)
            rec.record_can(position, T0_NS + (2 * i + 1) * 1000, "rx")
    return load(path).can_frames


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
