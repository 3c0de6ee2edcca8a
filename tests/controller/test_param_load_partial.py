"""``hil param load/diff`` of a partial TOML file and options an action would ignore: the
controller is a real :class:`~rt_controller.calibration.link.ParameterServer` played in-process
(:mod:`tests.support.param_link`) behind ``hil param``'s zenoh session."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

import hal.zenoh_session
from hal.config import RigConfig
from rt_controller.calibration.link import ParameterServer
from rt_controller.calibration.parameters import ParameterService
from rt_controller.cli import main
from tests.support.param_link import KEY, LoopbackLink


class Rig(LoopbackLink):
    """The rig's parameter link, its controller started with ``--law pbc``."""

    def __init__(self) -> None:
        super().__init__()
        cfg = RigConfig()
        cfg = replace(cfg, controller=replace(cfg.controller, law="pbc"))
        self.service = ParameterService(cfg)
        self.server = ParameterServer(self.service, KEY)

    def close(self) -> None:
        pass


@pytest.fixture
def rig(monkeypatch) -> Rig:
    link = Rig()
    monkeypatch.setattr(hal.zenoh_session, "open_session", lambda *a, **kw: link)
    return link


def _param(tmp_path: Path, *argv: str) -> int:
    key = tmp_path / "rig.key"
    key.write_text(KEY.hex() + "\n")
    key.chmod(0o600)
    return main(["param", *argv, "--key-file", str(key), "--timeout", "5"])


def test_load_of_a_partial_file_changes_only_the_keys_it_sets(rig, tmp_path, capsys):
    """A file that sets gains.kp alone must not switch the law back to the embedded default."""
    tuned = tmp_path / "tuned.toml"
    tuned.write_text("[gains]\nkp = 0.31\n")
    assert _param(tmp_path, "diff", str(tuned)) == 0
    assert capsys.readouterr().out == "gains.kp: running 0.13, file 0.31\n"
    assert _param(tmp_path, "load", str(tuned)) == 0
    assert "controller.law" not in capsys.readouterr().err
    assert rig.service.cfg.controller.law == "pbc" and rig.service.cfg.gains.kp == 0.31


def test_load_names_the_keys_it_cannot_apply_online(rig, tmp_path, capsys):
    """A rate in the file is not silently dropped: the note names it and both values."""
    tuned = tmp_path / "tuned.toml"
    tuned.write_text("[gains]\nkp = 0.31\n\n[rates]\ncontrol_hz = 100\n")
    assert _param(tmp_path, "load", str(tuned)) == 0
    err = capsys.readouterr().err
    assert "rates.control_hz (running 50.0, file 100.0)" in err and "restart" in err
    assert rig.service.cfg.rates.control_hz == 50.0 and rig.service.cfg.gains.kp == 0.31


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (("get", "-o", "OUT"), "get: -o/--out is for dump only"),
        (("set", "gains.kp=0.2", "-o", "OUT"), "set: -o/--out is for dump only"),
        (("get", "--at-tick", "5"), "get: --at-tick is for set, load and the actions only"),
        (("dump", "tuned.toml"), "dump takes no ARG, got 'tuned.toml'"),
    ],
)
def test_an_option_the_action_would_ignore_is_refused(rig, tmp_path, capsys, argv, said):
    argv = tuple(str(tmp_path / a) if a == "OUT" else a for a in argv)
    assert _param(tmp_path, *argv) == 2
    out = capsys.readouterr()
    assert out.out == "" and out.err.startswith(f"hil param: error: {said}")
    assert not (tmp_path / "OUT").exists() and rig.service.cfg.gains.kp == 0.13


def test_diff_json_is_one_json_object(rig, tmp_path, capsys):
    """``--json`` ("print the answer as JSON") was ignored by diff: text lines on stdout."""
    import json

    tuned = tmp_path / "tuned.toml"
    tuned.write_text("[gains]\nkp = 0.31\n")
    assert _param(tmp_path, "diff", str(tuned), "--json") == 0
    got = json.loads(capsys.readouterr().out)
    assert got == {"param_set": 0, "differ": {"gains.kp": {"running": 0.13, "file": 0.31}}}


def test_dump_json_is_refused_rather_than_printing_toml(rig, tmp_path, capsys):
    assert _param(tmp_path, "dump", "--json") == 2
    out = capsys.readouterr()
    assert out.out == "" and out.err.startswith("hil param: error: dump: --json does not apply")


def test_load_json_with_nothing_to_change_still_prints_one_object(rig, tmp_path, capsys):
    import json

    same = tmp_path / "same.toml"
    same.write_text("[gains]\nkp = 0.13\n")  # the running value
    assert _param(tmp_path, "load", str(same), "--json") == 0
    out, err = capsys.readouterr()
    assert json.loads(out) == {"param_set": 0, "changes": []}
    assert "nothing to change" in err
