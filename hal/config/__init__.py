"""Rig configuration: one TOML format for robot, camera, gains, scenario, rates and transports.

Every section is a frozen dataclass whose defaults are the paper's numbers (Pelican arm, the
paper's gains of eq. 34, the "paper" scenario). :func:`load_config` validates a file once at
start-up and raises :class:`~hal.errors.HalConfigError` naming the offending key. The config lives
in :mod:`hal` because both sides of the rig (controller and emulator) read the same file.

The package's modules, by concern: the sections of the plant (``plant.py``), of the controller
(``control.py``), of the experiment (``experiment.py``) and of the rig's other parts
(``devices.py``); the whole :class:`RigConfig` and its loading (``rig.py``); the ranges
(``ranges.py``) and the cross-field checks (``validation.py``). This module re-exports the
public API.
"""

from hal.config.cia402 import Cia402Config
from hal.config.control import LAW_NAMES, ControllerConfig, GainsConfig, RhcConfig
from hal.config.devices import DspConfig, TransportConfig, VisionConfig
from hal.config.experiment import RatesConfig, ScenarioConfig
from hal.config.hardware import PROFILES, HardwareConfig
from hal.config.plant import CameraConfig, PlantConfig, RobotConfig, plant_view
from hal.config.rig import (
    RETIRED_KEYS,
    RigConfig,
    config_from_dict,
    config_from_json,
    load_config,
    read_text_file,
)
from hal.config.validation import image_noise_error, validate
from hal.config.values import Mat2, Vec2

__all__ = [
    "LAW_NAMES",
    "PROFILES",
    "RETIRED_KEYS",
    "CameraConfig",
    "Cia402Config",
    "ControllerConfig",
    "DspConfig",
    "GainsConfig",
    "HardwareConfig",
    "Mat2",
    "PlantConfig",
    "RatesConfig",
    "RhcConfig",
    "RigConfig",
    "RobotConfig",
    "ScenarioConfig",
    "TransportConfig",
    "Vec2",
    "VisionConfig",
    "config_from_dict",
    "config_from_json",
    "image_noise_error",
    "load_config",
    "plant_view",
    "read_text_file",
    "validate",
]
