"""The shipped EDS of the CiA 402 drive: canopen reads it, it round-trips, it says CST and INT16."""

from __future__ import annotations

import canopen
import pytest
from canopen.objectdictionary import ODVariable, datatypes

from hal import cia402_od as od_table

NODE_ID = 5


def _variables(od: canopen.ObjectDictionary) -> dict[tuple[int, int], ODVariable]:
    out = {}
    for index in od:
        obj = od[index]
        members = [obj] if isinstance(obj, ODVariable) else [obj[s] for s in obj.subindices]
        for var in members:
            out[var.index, var.subindex] = var
    return out


def _fields(var: ODVariable) -> tuple:
    return (var.name, var.data_type, var.access_type, var.default, var.pdo_mappable, var.unit)


def test_the_shipped_eds_is_the_table_exported():
    assert od_table.EDS_PATH.read_text() == od_table.eds_text(), (
        "hal/cia402_drive.eds is stale: run python scripts/gen_docs.py"
    )


def test_canopen_imports_the_eds_and_every_object_round_trips():
    imported = _variables(canopen.import_od(str(od_table.EDS_PATH), NODE_ID))
    table = _variables(od_table.build_od(NODE_ID))
    assert imported.keys() == table.keys()
    for key, var in table.items():
        assert _fields(imported[key]) == _fields(var), f"0x{key[0]:04X}:{key[1]}"


def test_export_of_the_imported_eds_gives_the_same_objects(tmp_path):
    first = canopen.import_od(str(od_table.EDS_PATH), NODE_ID)
    path = tmp_path / "again.eds"
    canopen.export_od(first, str(path), doc_type="eds")
    again = _variables(canopen.import_od(str(path), NODE_ID))
    assert {k: _fields(v) for k, v in again.items()} == {
        k: _fields(v) for k, v in _variables(first).items()
    }


def test_the_eds_advertises_cyclic_synchronous_torque():
    od = canopen.import_od(str(od_table.EDS_PATH), NODE_ID)
    supported = od[od_table.SUPPORTED_MODES].default
    assert supported & od_table.CST_SUPPORTED_BIT
    assert od_table.CST_SUPPORTED_BIT == 1 << 9  # CiA 402: bit 9 = cst
    assert od[od_table.MODES_OF_OPERATION].data_type == datatypes.INTEGER8


@pytest.mark.parametrize("index", [od_table.TARGET_TORQUE, od_table.TORQUE_ACTUAL])
def test_target_and_actual_torque_are_int16(index):
    od = canopen.import_od(str(od_table.EDS_PATH), NODE_ID)
    assert od[index].data_type == datatypes.INTEGER16
    assert od[index].pdo_mappable


def test_cob_ids_follow_the_node_id_and_the_default_mapping_is_the_issues():
    od = canopen.import_od(str(od_table.EDS_PATH), NODE_ID)
    assert od[0x1400][1].default == 0x200 + NODE_ID
    assert od[0x1800][1].default == 0x180 + NODE_ID
    assert od[0x1801][1].default == 0x280 + NODE_ID
    assert od[0x1401][1].default & od_table.PDO_DISABLED
    assert [od[0x1600][s].default for s in (1, 2)] == [0x60400010, 0x60710010]
    assert [od[0x1A00][s].default for s in (1, 2)] == [0x60410010, 0x60640020]
    assert [od[0x1A01][s].default for s in (1, 2)] == [0x606C0020, 0x60770010]
    assert od[0x60C2][2].default == -3


def test_increments_per_rad_from_encoder_and_gear():
    assert od_table.increments_per_rad(1 << 20) == pytest.approx((1 << 20) / 6.283185307179586)
    assert od_table.increments_per_rad(4096, 1, 50, 1) == pytest.approx(4096 * 50 / 6.2831853)
