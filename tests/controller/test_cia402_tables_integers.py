"""A ``cia402`` log's CANopen tables keep their integers: ``node``, ``statusword``, SDO
``index`` and ``sdo_value``, ... are nullable ``Int64`` columns of ``run.can_frames`` and
``run.canopen_frames`` (``<NA>`` in the frames without them), as the DBC's integer signals
of a ``dsp`` log are, and ``hil export`` writes them as integers (csv digits, parquet int64)."""

from __future__ import annotations

import struct

import can
import pytest

from hal.config import RigConfig
from rt_controller.logs import load
from rt_controller.logs.export import export
from rt_controller.runtime.recorder import CycleRecorder

pytest.importorskip("pandas")

CIA402 = RigConfig().with_overrides({"hardware.profile": "cia402"})
FRAMES = [  # (direction, COB-ID, payload)
    ("tx", 0x601, struct.pack("<BHBI", 0x40, 0x1018, 1, 0)),  # read the vendor id
    ("rx", 0x581, struct.pack("<BHBI", 0x43, 0x1018, 1, 0xFFFFFFFF)),
    ("tx", 0x201, struct.pack("<Hh", 0x000F, -300)),
    ("tx", 0x080, b""),  # SYNC: no node, no fields
    ("rx", 0x181, struct.pack("<Hi", 0x1237, 123456)),
]
INTEGERS = ("node", "index", "subindex", "sdo_value", "controlword", "statusword")


def _log(path):
    with CycleRecorder(path, CIA402) as rec:
        for i, (direction, cob_id, data) in enumerate(FRAMES):
            msg = can.Message(arbitration_id=cob_id, data=data, is_extended_id=False)
            rec.record_can(msg, 1_000_000 + 1_000 * i, direction)
    return path


@pytest.mark.parametrize("table", ["can_frames", "canopen_frames"])
def test_canopen_integer_fields_are_nullable_integers(tmp_path, table):
    df = getattr(load(_log(tmp_path / "c.mcap")), table)
    for name in INTEGERS:
        assert str(df[name].dtype) == "Int64", (name, df[name].dtype)
    assert df["statusword"].dropna().tolist() == [0x1237]
    assert int(df["statusword"].dropna().iloc[0]) & 0x6F == 0x27  # bit masks work
    assert df["sdo_value"].dropna().tolist() == [0xFFFFFFFF]
    assert df["node"].isna().sum() == 1  # the SYNC


@pytest.mark.parametrize("topic", ["can", "canopen"])
def test_export_writes_canopen_integers_as_integers(tmp_path, topic):
    pq = pytest.importorskip("pyarrow.parquet")
    run = load(_log(tmp_path / "c.mcap"))
    csv, parquet = tmp_path / f"{topic}.csv", tmp_path / f"{topic}.parquet"
    export(run, "csv", {topic: csv})
    export(run, "parquet", {topic: parquet})
    header, *rows = [line.split(",") for line in csv.read_text().splitlines()]
    node = [row[header.index("node")] for row in rows]
    assert node == ["1", "1", "1", "", "1"]
    value = [row[header.index("sdo_value")] for row in rows]
    assert "4294967295" in value and not any(v.endswith(".0") for v in value)
    schema = pq.read_schema(parquet)
    for name in INTEGERS:
        assert str(schema.field(name).type) == "int64", name
