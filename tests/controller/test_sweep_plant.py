"""Model mismatch (``[plant]``): the emulated plant differs from the nominal model."""

from __future__ import annotations

import numpy as np
import pytest

from hal.config import RigConfig, config_from_dict, config_from_json, plant_view
from hal.errors import HalConfigError
from plant_emulator.world import World
from rt_controller.control.model import NominalModel


def test_nominal_plant_is_the_config_itself():
    cfg = RigConfig()
    assert plant_view(cfg) is cfg
    assert World(cfg).cfg == cfg


def test_theta_factors_scale_the_plant_only():
    cfg = config_from_dict({"plant": {"theta1": 1.2, "theta2": 0.8, "theta3": 1.1}})
    t = np.array(RigConfig().robot.theta)
    plant = np.array(plant_view(cfg).robot.theta)
    assert plant == pytest.approx(t * [1.2, 0.8, 1.1], rel=1e-12)
    nominal = NominalModel.from_config(cfg)  # the controller's model ignores [plant]
    assert (nominal.theta1, nominal.theta2, nominal.theta3) == pytest.approx(tuple(t))
    assert plant_view(cfg).plant.nominal


def test_camera_factors_change_the_emulators_gain_and_keep_f0():
    cfg = config_from_dict({"plant": {"z_wo": 1.25, "s_lambda": 0.9}})
    world = World(cfg)
    assert world.cfg.camera.gain == pytest.approx(RigConfig().camera.gain * 0.9 / 1.25)
    assert NominalModel.from_config(cfg).gain == pytest.approx(RigConfig().camera.gain)
    # the target is placed where the plant's camera sees scenario.f0
    assert world.true_features() == pytest.approx(np.array(cfg.scenario.f0))


def test_the_plant_section_round_trips_through_json():
    cfg = config_from_dict({"plant": {"z_wo": 1.1}})
    assert config_from_json(cfg.to_json()) == cfg


@pytest.mark.parametrize(
    ("plant", "needle"),
    [
        ({"mass": 2.0}, "unknown key plant.mass"),
        ({"z_wo": 0.0}, "plant.z_wo"),
        ({"theta1": 50.0}, "plant.theta1"),
        ({"theta1": 0.5}, "inertia I1"),
        ({"theta2": "big"}, "plant.theta2: expected a number"),
    ],
)
def test_bad_plant_values_are_refused(plant, needle):
    with pytest.raises(HalConfigError, match=needle):
        config_from_dict({"plant": plant})
