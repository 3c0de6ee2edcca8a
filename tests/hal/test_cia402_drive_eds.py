"""``cia402.eds_1`` / ``eds_2``: the EDS of each real drive, as its vendor ships it. Checked when
the configuration loads (one line naming the key, the file and what is wrong); an EDS lacking
an object the master needs never reaches a boot. And ``hil cia402 check`` says what it waits
for while no drive answers, naming every node that never did."""

from __future__ import annotations

import threading
from pathlib import Path
from types import SimpleNamespace

import canopen
import pytest

from hal.cia402_master import boot
from hal.cia402_od import EDS_PATH, TARGET_TORQUE, TORQUE_ACTUAL
from hal.config import load_config
from hal.errors import HalConfigError, HalTimeoutError
from rt_controller.cli import main
from tests.support import start_hil, stop_hil


def export(od: canopen.ObjectDictionary, path: Path) -> Path:
    canopen.export_od(od, str(path), doc_type="eds")
    return path


def shipped() -> canopen.ObjectDictionary:
    return canopen.import_od(str(EDS_PATH), 1)


def vendor_eds(tmp_path: Path) -> Path:
    """The shipped EDS exported again with a manufacturer-specific object, as a vendor's is."""
    od = shipped()
    extra = canopen.objectdictionary.ODVariable("Vendor current loop gain", 0x2000)
    extra.data_type = canopen.objectdictionary.UNSIGNED32
    extra.access_type = "rw"
    extra.default = 1234
    od.add_object(extra)
    return export(od, tmp_path / "vendor drive.eds")


def config(tmp_path: Path, **keys: str) -> Path:
    body = "".join(f'{k} = "{v}"\n' for k, v in keys.items())
    path = tmp_path / "rig.toml"
    path.write_text(f"[cia402]\n{body}")
    return path


def check_fails_in_one_line(conf: Path, capsys) -> str:
    """``hil cia402 check`` on ``conf``: exit 2 and one stderr line, before any bus is used."""
    assert main(["cia402", "check", "--can", "virtual:eds-nobody", "--config", str(conf)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    return err.strip()


def test_an_eds_without_target_torque_is_refused_naming_key_file_and_object(tmp_path, capsys):
    od = shipped()
    del od[TARGET_TORQUE]
    eds = export(od, tmp_path / "no6071.eds")
    conf = config(tmp_path, eds_1=str(eds))
    want = (
        f"cia402.eds_1: {eds} lacks 0x6071 (target torque) that the cia402 master reads, "
        "writes or maps"
    )
    with pytest.raises(HalConfigError) as caught:
        load_config(conf)
    assert str(caught.value) == f"{conf}: {want}"
    assert check_fails_in_one_line(conf, capsys) == f"hil cia402 check: error: {conf}: {want}"


def test_every_missing_object_is_named_in_the_one_line(tmp_path):
    od = shipped()
    del od[TARGET_TORQUE], od[TORQUE_ACTUAL]
    eds = export(od, tmp_path / "no-torques.eds")
    with pytest.raises(
        HalConfigError,
        match=r"cia402\.eds_2: .* lacks 0x6071 \(target torque\), "
        r"0x6077 \(torque actual\) that",
    ):
        load_config(config(tmp_path, eds_2=str(eds)))


@pytest.mark.parametrize(
    "content",
    [b"this is no EDS\n", b"\x00\xff\x17garbage" * 40, b"[1000]\nParameterName=x\n"],
    ids=["text", "binary", "incomplete"],
)
def test_a_garbage_eds_is_refused_in_one_line(tmp_path, capsys, content):
    eds = tmp_path / "garbage.eds"
    eds.write_bytes(content)
    err = check_fails_in_one_line(config(tmp_path, eds_1=str(eds)), capsys)
    assert f"cia402.eds_1: {eds} is not an EDS canopen can read: " in err


def test_a_missing_eds_is_refused_in_one_line(tmp_path, capsys):
    eds = tmp_path / "nowhere.eds"
    err = check_fails_in_one_line(config(tmp_path, eds_2=str(eds)), capsys)
    assert err.endswith(f"cia402.eds_2: cannot read {eds}: No such file or directory")


def test_a_mapped_object_of_the_wrong_type_is_refused(tmp_path):
    od = shipped()
    od[TARGET_TORQUE].data_type = canopen.objectdictionary.INTEGER32
    eds = export(od, tmp_path / "int32-torque.eds")
    with pytest.raises(HalConfigError, match=r"0x6071 \(target torque\) is INTEGER32, not "):
        load_config(config(tmp_path, eds_1=str(eds)))


def test_a_vendor_eds_with_an_extra_object_is_accepted(tmp_path):
    eds = vendor_eds(tmp_path)
    cfg = load_config(config(tmp_path, eds_1=str(eds), eds_2=str(eds)))
    assert (cfg.cia402.eds_1, cfg.cia402.eds_2) == (str(eds), str(eds))


def test_the_default_is_the_shipped_eds():
    cfg = load_config()
    assert (cfg.cia402.eds_1, cfg.cia402.eds_2) == ("", "")


class SilentNode:
    """A node whose NMT command is sent and which boots (``boots``) or stays silent."""

    def __init__(self, node_id: int, booted: dict[int, threading.Event], boots: bool) -> None:
        self.id = node_id
        self.booted, self.boots = booted, boots

    @property
    def nmt(self) -> SimpleNamespace:
        node = self

        class Nmt:
            @property
            def state(self) -> str:
                return "none"

            @state.setter
            def state(self, _value: str) -> None:
                if node.boots:
                    node.booted[node.id].set()

        return Nmt()


@pytest.mark.parametrize("booting", [(), (1,), (2,)], ids=["none", "node-1", "node-2"])
def test_the_boot_timeout_names_every_node_that_never_answered(booting):
    booted = {i: threading.Event() for i in (1, 2, 3)}
    nodes = [SilentNode(i, booted, i in booting) for i in (1, 2, 3)]
    silent = ", ".join(str(i) for i in (1, 2, 3) if i not in booting)
    with pytest.raises(HalTimeoutError) as caught:
        boot.reset_communication(nodes, booted, 0.1)
    assert str(caught.value).startswith(f"nodes {silent} sent no boot-up within 0.1 s"), caught


@pytest.mark.parametrize("given", ["shipped", "vendor"])
def test_hil_cia402_check_says_what_it_waits_for_before_waiting(tmp_path, given):
    """No drive on the bus: the first line on stderr comes at the start (not after the boot
    timeout) and says what the command waits for, on which node ids, with which EDS."""
    args = ["cia402", "check", "--can", "virtual:eds-nobody"]
    eds = "the shipped hal/cia402_drive.eds"
    if given == "vendor":
        eds = str(vendor_eds(tmp_path))
        args += ["--config", str(config(tmp_path, eds_1=eds))]
    proc = start_hil(args, capture=True)
    try:
        first = proc.stderr.readline()
    finally:
        stop_hil(proc)
    assert first.startswith("hil cia402 check: NMT reset communication sent, waiting up to "), first
    assert f"s for the boot-up of node 1 (EDS {eds}) and node 2 (EDS the shipped " in first, first


def test_a_relative_path_is_relative_to_the_working_directory(tmp_path, monkeypatch):
    od = shipped()
    del od[TARGET_TORQUE]
    (tmp_path / "drives").mkdir()
    export(od, tmp_path / "drives" / "x.eds")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(HalConfigError, match=r"cia402\.eds_1: drives/x\.eds lacks 0x6071 "):
        load_config(config(tmp_path, eds_1="drives/x.eds"))
    monkeypatch.chdir(tmp_path / "drives")
    with pytest.raises(HalConfigError, match=r"cia402\.eds_1: cannot read drives/x\.eds: No such"):
        load_config(config(tmp_path, eds_1="drives/x.eds"))
