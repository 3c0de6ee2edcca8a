"""A log's embedded configuration names the lab's drive EDS files: read back on a host
without them (a laptop), it is still the run's configuration, not "not a valid configuration"."""

from __future__ import annotations

import json

import pytest

from hal.config import RigConfig, config_from_dict, config_from_json
from hal.errors import HalConfigError


def test_a_logs_config_naming_an_absent_eds_reads_back():
    data = RigConfig().to_dict()
    data["cia402"]["eds_1"] = "/lab/drives/servo.eds"
    cfg = config_from_json(json.dumps(data))
    assert cfg.cia402.eds_1 == "/lab/drives/servo.eds"
    with pytest.raises(HalConfigError, match=r"cia402\.eds_1: cannot read /lab/drives/servo\.eds"):
        config_from_dict(data)  # a config the user gives is still checked
