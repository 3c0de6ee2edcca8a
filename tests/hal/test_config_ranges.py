"""Input hardening of hal.config: every numeric setting has a sane range, NaN/inf are refused,
non-UTF-8 files and embedded (log) configs get the same one-line HalConfigError naming the key,
and command-line overrides (``with_overrides``) are checked exactly like a file."""

from __future__ import annotations

import math

import pytest

from hal.config import RigConfig, config_from_dict, config_from_json, load_config
from hal.errors import HalConfigError

BAD = [
    # (key, value)
    ("rhc.steps", 1_000_000_000),
    ("rhc.steps", 0),
    ("rhc.steps", 201),
    ("rhc.horizon", 1e6),
    ("rhc.horizon", 0.0),
    ("rhc.kmax", 51),
    ("rhc.zeta", math.nan),
    ("rates.physics_hz", 1e300),
    ("rates.control_hz", 1e-9),
    ("rates.control_hz", math.inf),
    ("rates.status_hz", 1e-9),
    ("controller.feature_timeout_s", 1e12),
    ("controller.state_timeout_s", 1e12),
    ("controller.feature_timeout_s", math.nan),
    ("controller.max_clock_skew_s", -0.001),
    ("controller.max_clock_skew_s", 5.0),
    ("dsp.watchdog_periods", 1e12),
    ("dsp.watchdog_periods", 0.5),
    ("dsp.q_max", [math.inf, 2.6]),
    ("dsp.q_max", [math.pi, 60.0]),
    ("dsp.dq_max", [0.0, 8.0]),
    ("dsp.dq_max", [-math.inf, 8.0]),
    ("robot.tau_max", [1e300, 15.0]),
    ("camera.latency_s", 1e9),
    ("camera.seed", -1),
    ("scenario.jump_time", math.nan),
]


def toml_value(value: object) -> str:
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    return repr(value)


def check_one_line(err: pytest.ExceptionInfo[HalConfigError], key: str) -> None:
    text = str(err.value)
    assert key in text, text
    assert "\n" not in text
    assert err.value.__cause__ is None or isinstance(err.value.__cause__, HalConfigError)


@pytest.mark.parametrize(("key", "value"), BAD)
def test_bad_value_in_a_file_names_the_key(tmp_path, key, value):
    section, name = key.split(".")
    path = tmp_path / "rig.toml"
    path.write_text(f"[{section}]\n{name} = {toml_value(value)}\n", encoding="utf-8")
    with pytest.raises(HalConfigError) as err:
        load_config(path)
    check_one_line(err, key)
    assert str(path) in str(err.value)


@pytest.mark.parametrize(("key", "value"), BAD)
def test_bad_value_as_a_command_line_override_names_the_key(key, value):
    with pytest.raises(HalConfigError) as err:
        RigConfig().with_overrides({key: value})
    check_one_line(err, key)


@pytest.mark.parametrize(("key", "value"), BAD)
def test_bad_value_in_a_log_embedded_config_names_the_key(key, value):
    data = RigConfig().to_dict()
    section, name = key.split(".")
    data[section][name] = value
    with pytest.raises(HalConfigError) as err:
        config_from_dict(data, source="log metadata")
    check_one_line(err, key)
    assert str(err.value).startswith("log metadata: ")


def test_embedded_json_with_a_huge_steps_value_fails_before_allocating():
    text = RigConfig().to_json().replace('"steps": 10', '"steps": 1000000000')
    with pytest.raises(HalConfigError, match=r"^hil log: rhc\.steps: .*out of range"):
        config_from_json(text, source="hil log")
    with pytest.raises(HalConfigError, match="not valid JSON"):
        config_from_json(b"\xff\xfe{", source="hil log")


def test_non_utf8_file_is_one_line(tmp_path):
    path = tmp_path / "rig.toml"
    path.write_bytes(b"[rhc]\nsteps = 10\n# caf\xe9\n")
    with pytest.raises(HalConfigError) as err:
        load_config(path)
    text = str(err.value)
    assert "not UTF-8" in text and "0xe9" in text and "\n" not in text
    assert err.value.__cause__ is None and err.value.__suppress_context__


def test_bad_toml_error_is_one_line(tmp_path):
    path = tmp_path / "rig.toml"
    path.write_text("[rhc\nsteps = \n", encoding="utf-8")
    with pytest.raises(HalConfigError) as err:
        load_config(path)
    assert "not valid TOML" in str(err.value) and "\n" not in str(err.value)


def test_defaults_and_boundaries_are_accepted():
    cfg = RigConfig().with_overrides(
        {
            "rhc.steps": 200,
            "rhc.kmax": 50,
            "rhc.horizon": 10.0,
            "dsp.watchdog_periods": 100,
            "controller.feature_timeout_s": 10.0,
            "rates.control_hz": 2000.0,
            "rates.physics_hz": 100_000.0,
        }
    )
    assert cfg.rhc.steps == 200 and cfg.rates.physics_hz == 100_000.0
    d = RigConfig().dsp
    assert d.q_min[0] < 0 < d.q_max[0] and all(v > 0 for v in d.dq_max)


def test_limits_must_be_ordered_and_contain_the_start_pose():
    with pytest.raises(HalConfigError, match=r"dsp\.q_min"):
        RigConfig().with_overrides({"dsp.q_min": [1.0, -2.6], "dsp.q_max": [0.5, 2.6]})
    with pytest.raises(HalConfigError, match=r"scenario\.q0"):
        RigConfig().with_overrides({"dsp.q_max": [0.1, 2.6]})  # q0[0] = pi/6 > 0.1
