"""A new user's first config files: the mistakes of a first TOML file (a huge number, a key
outside its section, a misspelt key or section, a value of the wrong type) each end in one line
that names the key and says what to write, and the TOML the rig writes for its children (the
config with its command-line overrides) reads back whatever the strings hold."""

from __future__ import annotations

import re

import pytest

from hal.config import RigConfig, config_from_dict, load_config
from hal.errors import HalConfigError
from rt_controller.cli import main
from rt_controller.config_rules import config_toml

HUGE = "1" + "0" * 400  # a valid TOML integer no float holds


def write(tmp_path, text: str):
    path = tmp_path / "rig.toml"
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.parametrize(
    ("text", "key"),
    [
        (f"[rates]\ncontrol_hz = {HUGE}\n", "rates.control_hz"),
        (f"[rhc]\nhorizon = {HUGE}\n", "rhc.horizon"),
        (f"[controller]\ncpu = {HUGE}\n", "controller.cpu"),
        (f"[camera]\nseed = {HUGE}\n", "camera.seed"),
        (f"[gains]\nalpha = [{HUGE}, 1]\n", "gains.alpha"),
    ],
)
def test_a_huge_integer_is_refused_naming_the_key(tmp_path, text, key):
    with pytest.raises(HalConfigError) as err:
        load_config(write(tmp_path, text))
    assert str(err.value).startswith(f"{tmp_path / 'rig.toml'}: {key}"), err.value
    assert "\n" not in str(err.value)


def test_hil_simulate_refuses_a_huge_integer_in_one_line(tmp_path, capsys):
    conf = write(tmp_path, f"[rates]\ncontrol_hz = {HUGE}\n")
    assert main(["simulate", "--config", str(conf), "--duration", "0.1", "-q"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "rates.control_hz" in err, err


def test_an_integer_range_is_shown_exactly(tmp_path):
    with pytest.raises(HalConfigError) as err:
        load_config(write(tmp_path, "[camera]\nseed = -1\n"))
    assert "camera.seed: -1 is out of range [0, 9223372036854775807]" in str(err.value)


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("steps = 20\n", "steps = 20 is outside any section: write it under [rhc]"),
        ("rt_priority = 5\n", "write it under [controller], [dsp] or [vision]"),
        ("speed = 5\n", "unknown key speed outside any section"),
    ],
)
def test_a_key_outside_its_section_says_where_it_goes(tmp_path, text, needle):
    with pytest.raises(HalConfigError) as err:
        load_config(write(tmp_path, text))
    assert needle in str(err.value), err.value
    assert "unknown section" not in str(err.value)


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("[rhc]\nstepz = 20\n", "unknown key rhc.stepz (did you mean steps?"),
        ("[rhcc]\nsteps = 20\n", "unknown section [rhcc] (did you mean [rhc]?"),
        ("[rhc]\ngarbage = 20\n", "unknown key rhc.garbage (known keys: horizon,"),
        ("[rhc]\nlaw = 'rhc'\n", "unknown key rhc.law (law is a key of [controller]; known"),
    ],
)
def test_a_misspelt_name_gets_the_near_one(tmp_path, text, needle):
    with pytest.raises(HalConfigError) as err:
        load_config(write(tmp_path, text))
    assert needle in str(err.value), err.value


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("[rhc]\nsteps = true\n", "rhc.steps: expected an integer, got true"),
        ("[robot]\ntau_max = [true, 15.0]\n", "robot.tau_max[0]: expected a number, got true"),
        ("[rhc]\nsteps = 1979-05-27\n", "rhc.steps: expected an integer, got 1979-05-27"),
    ],
)
def test_a_wrong_type_is_shown_as_toml_writes_it(tmp_path, text, needle):
    with pytest.raises(HalConfigError) as err:
        load_config(write(tmp_path, text))
    assert needle in str(err.value), err.value


@pytest.mark.parametrize(
    "value",
    ["logs\nnew", "C:\\temp\\new", 'a "quoted" dir', "tab\there", "bell\x07 del\x7f", "naïve"],
)
def test_the_toml_written_for_the_children_reads_back(tmp_path, value):
    data = RigConfig().to_dict()
    data["controller"]["log_dir"] = value
    cfg = config_from_dict(data)
    path = write(tmp_path, config_toml(cfg, header="written for a child"))
    assert load_config(path) == cfg


@pytest.mark.parametrize(
    ("rates", "suggested"),
    [
        ("control_hz = 300\n", "1200"),
        ("control_hz = 30\nphysics_hz = 1000\n", "1020"),
        ("control_hz = 1999\nphysics_hz = 100000\n", "99950"),  # the multiple below: in range
    ],
)
def test_a_control_rate_off_the_physics_rate_names_a_physics_rate_that_fits(
    tmp_path, rates, suggested
):
    with pytest.raises(HalConfigError) as err:
        load_config(write(tmp_path, f"[rates]\n{rates}"))
    assert str(err.value).endswith(f"; e.g. rates.physics_hz = {suggested})"), err.value
    control = rates.splitlines()[0]
    fixed = load_config(write(tmp_path, f"[rates]\n{control}\nphysics_hz = {suggested}\n"))
    assert fixed.rates.physics_hz == float(suggested)


QUOTED_FILES = {
    "bad.toml": "[gains]\nalpha = [[0.05, 0.0], [0.0, -0.1]]\n",
    "misspelt.toml": "[rhc]\nstepz = 10\n",
    "toplevel.toml": "steps = 10\n",
    "rate.toml": "[rates]\ncontrol_hz = 300\n",
}
"""The files behind the error lines the configuration page quotes."""


def test_every_error_line_the_configuration_page_quotes_is_what_hil_prints(
    tmp_path, monkeypatch, capsys
):
    from tests.support import REPO

    text = (REPO / "docs" / "concepts" / "configuration.md").read_text(encoding="utf-8")
    quoted = re.findall(r"^hil simulate: error: ([\w.]+): .*$", text, flags=re.M)
    assert sorted(quoted) == sorted(QUOTED_FILES), quoted
    monkeypatch.chdir(tmp_path)
    for name, body in QUOTED_FILES.items():
        (tmp_path / name).write_text(body, encoding="utf-8")
        assert main(["simulate", "--config", name, "-q"]) == 2
        line = re.search(rf"^hil simulate: error: {re.escape(name)}: .*$", text, flags=re.M)
        assert capsys.readouterr().err.strip() == line.group(0)


@pytest.mark.parametrize(
    ("overrides", "line"),
    [
        ({"rhc": {"horizon": 0.0}}, "rhc.horizon: must be positive, got 0.0"),
        ({"rhc": {"steps": 0}}, "rhc.steps: must be at least 1, got 0"),
        ({"robot": {"tau_max": [1.0, -2.0]}}, "robot.tau_max: must be positive, got [1.0, -2.0]"),
    ],
)
def test_a_bound_error_repeats_the_value(overrides: dict, line: str) -> None:
    with pytest.raises(HalConfigError) as err:
        config_from_dict(overrides)
    assert line in str(err.value)


def test_a_spin_of_a_whole_period_is_refused() -> None:
    """The busy-wait before each deadline must leave time to wait and read ahead."""
    fast = {"rates": {"control_hz": 2000.0, "physics_hz": 4000.0}}
    assert config_from_dict({**fast, "controller": {"spin_us": 300.0}})  # the default fits
    with pytest.raises(HalConfigError) as err:
        config_from_dict({**fast, "controller": {"spin_us": 500.0}})
    assert "controller.spin_us: must be less than the control period (500 us" in str(err.value)
