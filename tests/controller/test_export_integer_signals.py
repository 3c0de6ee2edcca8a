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

from rt_controller.cli import main
from tests.support.can_log import TICKS, write_tick_log


@pytest.fixture
def log(tmp_path):
    return write_tick_log(tmp_path / "run.mcap")


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
