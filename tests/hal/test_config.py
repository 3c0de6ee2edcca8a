"""Configuration: defaults, the example file, and clear errors naming the bad key."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from hal.config import RigConfig, config_from_json, load_config
from hal.errors import HalConfigError

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "rig.toml"


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "rig.toml"
    p.write_text(text)
    return p


def test_defaults_are_design_numbers(cfg: RigConfig):
    assert cfg.camera.gain == pytest.approx(1230 / 0.9)
    assert cfg.robot.tau_max == (150.0, 15.0)
    t1, t2, t3 = cfg.robot.theta
    assert t1 == pytest.approx(6.5225 * 0.0983**2 + 2.0458 * 0.26**2 + 0.1213)
    assert t2 == pytest.approx(2.0458 * 0.0229**2 + 0.0116)
    assert t3 == pytest.approx(2.0458 * 0.26 * 0.0229)
    expected_r = [[0.13 / 4 / 0.05 + 0.01, 0], [0, 0.13 / 4 / 0.15 + 0.01]]
    np.testing.assert_allclose(cfg.gains.R, expected_r)


def test_example_file_equals_defaults(cfg: RigConfig):
    assert load_config(EXAMPLE) == cfg


def test_example_file_lists_every_key(cfg: RigConfig):
    """examples/rig.toml is the annotated list of every key with its default (the docs say so):
    a key left out of it still loads as its default, so only this test sees it missing."""
    with EXAMPLE.open("rb") as f:
        example = tomllib.load(f)
    missing = [
        f"{section}.{key}"
        for section, keys in cfg.to_dict().items()
        for key in keys
        if key not in example.get(section, {})
    ]
    assert not missing, missing


def test_json_round_trip(cfg: RigConfig):
    assert config_from_json(cfg.to_json()) == cfg


def test_partial_file_keeps_other_defaults(tmp_path):
    c = load_config(
        write(tmp_path, "[rates]\ncontrol_hz = 100\n[gains]\nalpha = [[0.1, 0.01], [0.01, 0.2]]\n")
    )
    assert c.rates.control_hz == 100.0
    assert c.gains.alpha == ((0.1, 0.01), (0.01, 0.2))
    assert c.robot == RigConfig().robot


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("[robot]\nmass = 3\n", "unknown key robot.mass"),
        ("[robt]\nl1 = 3\n", "unknown section [robt]"),
        ("[robot]\nl1 = 'long'\n", "robot.l1: expected a number"),
        ("[robot]\nl1 = true\n", "robot.l1: expected a number"),
        ("[robot]\nl1 = -0.1\n", "robot.l1: must be positive"),
        ("[robot]\ntau_max = [1, 2, 3]\n", "robot.tau_max: expected a list of 2 numbers"),
        ("[rhc]\nsteps = 2.5\n", "rhc.steps: expected an integer"),
        ("[scenario]\ndisturbance = 1\n", "scenario.disturbance: expected true or false"),
        ("[gains]\nalpha = [0.05, -0.1]\n", "gains.alpha: must be positive definite"),
        ("[gains]\nK = [[0.01, 0.02], [0.0, 0.01]]\n", "gains.K: must be symmetric"),
        ("[gains]\nK = [[1, 2], [2, 1]]\n", "gains.K: must be positive definite"),
        ("[gains]\nalpha = 'big'\n", "gains.alpha: expected a 2x2 matrix"),
        ("[rates]\ncontrol_hz = 0\n", "rates.control_hz: must be positive"),
        ("[rates]\ncontrol_hz = 2000\n", "rates.physics_hz: must be at least rates.control_hz"),
        ("[rates]\ncontrol_hz = 300\n", "rates.physics_hz: must be an integer multiple"),
        ("[rates]\nstate_hz = 5000\n", "rates.state_hz: cannot exceed"),
        ("[controller]\nlaw = 'lqr'\n", "controller.law: must be pbc, ioc or rhc"),
        ("[scenario]\nname = 'moon'\n", "scenario.name: unknown scenario"),
        ("[robot\n", "not valid TOML"),
        ("robot = 3\n", "[robot]: expected a table"),
    ],
)
def test_bad_files_name_the_key(tmp_path, text, needle):
    with pytest.raises(HalConfigError) as err:
        load_config(write(tmp_path, text))
    assert needle in str(err.value)
    assert str(tmp_path) in str(err.value)


def test_missing_file(tmp_path):
    with pytest.raises(HalConfigError, match="cannot read config file"):
        load_config(tmp_path / "nope.toml")


def test_error_is_also_a_value_error(tmp_path):
    with pytest.raises(ValueError, match=r"robot\.m1") as err:
        load_config(write(tmp_path, "[robot]\nm1 = -1\n"))
    assert isinstance(err.value, HalConfigError)  # the config's own error, caught as ValueError


def test_overrides_are_validated(cfg: RigConfig):
    assert cfg.with_overrides({"rates.control_hz": 100}).rates.control_hz == 100
    with pytest.raises(HalConfigError, match=r"unknown key rates\.speed"):
        cfg.with_overrides({"rates.speed": 1})
    with pytest.raises(HalConfigError, match="unknown config key"):
        cfg.with_overrides({"nothing": 1})


def test_a_retired_key_is_refused_in_a_file_with_its_reason_and_skipped_in_a_log(tmp_path):
    """Keys an older version had (hal.config.RETIRED_KEYS): a config file that still sets
    one gets one line saying why it went; a log written by that version still replays (its
    embedded config is read with them skipped)."""
    import json

    from hal.config import RETIRED_KEYS, RigConfig, config_from_json, load_config
    from hal.errors import HalConfigError

    for dotted, why in RETIRED_KEYS.items():
        section, key = dotted.split(".")
        path = tmp_path / f"{key}.toml"
        path.write_text(f"[{section}]\n{key} = 0\n")
        with pytest.raises(HalConfigError) as err:
            load_config(path)
        assert f"{dotted} was removed: {why}" in str(err.value)
    old = json.loads(RigConfig().to_json())
    old["controller"].update(state_wait_us=0.0, gil_switch_us=200.0, recorder="process")
    assert config_from_json(json.dumps(old)) == RigConfig()
