"""``hil export`` of the ``can`` table keeps integer DBC signals integers, as ``run.can_frames``
does: Parquet an Arrow integer column with nulls where a frame lacks the signal, CSV the
integer's digits and an empty cell there (never ``nan`` nor ``.0``); scaled signals stay
floats. MATLAB has no missing integer: ``.mat`` keeps doubles with NaN, exact to 2**53.
The log is written through the recorder's public seam (:class:`CycleRecorder`) with frames
encoded by the rig's codecs."""

from __future__ import annotations

import csv
import math

import pytest

from hal.can_codec import DspCodec
from hal.config import RigConfig
from rt_controller.cli import main
from rt_controller.runtime.recorder import CycleRecorder

T0_NS = 1_000_000_000
TICKS = (4_294_967_295, 4_294_967_294, 123_456_789)  # the widest integer signal: 32 bits


@pytest.fixture
def log(tmp_path):
    """Sync frames (``Tick``, ``Counter``) between JointPosition frames (``Q1``, ``Q2``,
    ``Sample``, no ``Tick``): ``Tick`` is present in some rows and absent in the others."""
    path = tmp_path / "run.mcap"
    dsp = DspCodec()
    info = {"clock": "lockstep", "can": "virtual", "zenoh": "tcp/127.0.0.1:1", "recorder": "thread"}
    with CycleRecorder(path, RigConfig(), run_info=info) as rec:
        for i, tick in enumerate(TICKS):
            rec.record_can(dsp.encode_sync(tick), T0_NS + 2 * i * 1000, "rx")
            position, _ = dsp.encode_state((0.25, -0.5), (0.0, 0.0), i)
            rec.record_can(position, T0_NS + (2 * i + 1) * 1000, "rx")
    return path


def export(log, fmt, tmp_path, capsys):
    out = tmp_path / fmt
    argv = ["export", str(log), "--format", fmt, "--topics", "can", "--out", str(out)]
    assert main(argv) == 0
    capsys.readouterr()
    return out


def test_parquet_integer_signal_is_an_arrow_integer_with_nulls(log, tmp_path, capsys):
    pa = pytest.importorskip("pyarrow")
    pq = pytest.importorskip("pyarrow.parquet")
    table = pq.read_table(export(log, "parquet", tmp_path, capsys) / "run.can.parquet")
    assert table.schema.field("Tick").type == pa.int64()
    assert table.column("Tick").null_count == len(TICKS)  # the JointPosition frames
    cols = table.to_pydict()
    assert cols["message"] == ["Sync", "JointPosition"] * len(TICKS)
    assert cols["Tick"] == [v for t in TICKS for v in (t, None)]  # exact ints, None between
    for name in ("Counter", "Sample", "Freshness", "Mac", "CRC"):
        assert pa.types.is_integer(table.schema.field(name).type), name
    assert table.schema.field("Q1").type == pa.float64()  # scaled: float, null where absent
    assert cols["Q1"][0] is None or math.isnan(cols["Q1"][0])
    assert cols["Q1"][1] == pytest.approx(0.25, abs=1e-5)
    assert table.schema.metadata[b"hil.topic"] == b"can"


def test_csv_integer_signal_is_digits_and_an_empty_cell(log, tmp_path, capsys):
    pytest.importorskip("pandas")
    path = export(log, "csv", tmp_path, capsys) / "run.can.csv"
    with path.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["Tick"] for r in rows] == [v for t in TICKS for v in (str(t), "")]
    assert rows[1]["Sample"] == "0" and rows[0]["Sample"] == ""


def test_mat_integer_signal_is_an_exact_double_with_nan(log, tmp_path, capsys):
    sio = pytest.importorskip("scipy.io")
    path = export(log, "mat", tmp_path, capsys) / "run.mat"
    frames = sio.loadmat(path, squeeze_me=True, struct_as_record=False)["can"]
    ticks = list(frames.Tick)
    assert ticks[0::2] == list(TICKS) and all(math.isnan(t) for t in ticks[1::2])
