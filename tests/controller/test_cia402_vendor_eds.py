"""A vendor's EDS (the shipped one exported again with a manufacturer-specific object, as a
drive vendor's file has them) given as ``cia402.eds_1`` / ``eds_2``: the master describes the
drives by it, boots the emulated drives with it, and ``hil cia402 check`` says which EDS each
node was given."""

from __future__ import annotations

import json

import can
import canopen
import pytest

from hal.cia402_master.master import Cia402Master
from hal.cia402_od import EDS_PATH
from hal.config import load_config
from rt_controller.cli import main
from tests.support.cia402 import FakeNow, drives_on_virtual_bus

VENDOR_INDEX = 0x2000


@pytest.fixture
def vendor(tmp_path):
    """(config file, EDS) with eds_1 the vendor's EDS, eds_2 empty (the shipped one)."""
    od = canopen.import_od(str(EDS_PATH), 1)
    extra = canopen.objectdictionary.ODVariable("Vendor current loop gain", VENDOR_INDEX)
    extra.data_type = canopen.objectdictionary.UNSIGNED32
    extra.access_type = "rw"
    extra.default = 1234
    od.add_object(extra)
    eds = tmp_path / "vendor.eds"
    canopen.export_od(od, str(eds), doc_type="eds")
    conf = tmp_path / "rig.toml"
    conf.write_text(f'[cia402]\neds_1 = "{eds}"\n')
    return conf, eds


def test_the_master_describes_each_drive_by_its_configured_eds_and_boots(vendor):
    conf, _eds = vendor
    cfg = load_config(conf)
    with drives_on_virtual_bus(cfg) as bench:
        bus = can.Bus(interface="virtual", channel=bench.master.bus.channel_id)
        master = Cia402Master.from_config(cfg, bus, now_ns=FakeNow())
        try:
            vendor_od, shipped_od = (n.object_dictionary for n in master.nodes)
            assert VENDOR_INDEX in vendor_od and VENDOR_INDEX not in shipped_od
            master.boot()
            assert [m.rated_torque_mnm for m in master.units] == [
                round(t * 1000) for t in cfg.cia402.rated_torque
            ]
            master.send(None)
            k = master.sync()  # TPDOs answer a SYNC only in NMT operational, mapped
            assert master.wait_tpdos(k, 5.0), master.diagnostics()
            assert master.joint_state().states == ("SWITCH ON DISABLED",) * 2
        finally:
            master.close()


def test_hil_cia402_check_says_which_eds_each_node_was_given(vendor, capsys):
    conf, eds = vendor
    with drives_on_virtual_bus(load_config(conf)) as bench:
        channel = bench.master.bus.channel_id
        argv = ["cia402", "check", "--can", f"virtual:{channel}", "--config", str(conf)]
        assert main([*argv, "--json"]) == 0
        out = capsys.readouterr()
        drives = json.loads(out.out)["drives"]
        assert [(d["node"], d["eds"]) for d in drives] == [
            (1, str(eds)),
            (2, "the shipped hal/cia402_drive.eds"),
        ]
        assert f"node 1 (EDS {eds}) and node 2 (EDS the shipped" in out.err
        assert main(argv) == 0
        lines = capsys.readouterr().out.splitlines()
        assert lines[0].startswith("node 1: ") and lines[0].endswith(f"; EDS {eds}")
        assert lines[1].endswith("; EDS the shipped hal/cia402_drive.eds")
