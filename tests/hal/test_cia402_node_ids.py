"""The drives' node ids in ``[cia402]``: distinct, and never the controller's own id (127,
its heartbeat's node), which made ``hil cia402 check`` end in canopen's traceback."""

from __future__ import annotations

import pytest

from hal.config import RigConfig
from hal.config.cia402 import CONTROLLER_NODE_ID
from hal.errors import HalConfigError
from rt_controller.cli import main


@pytest.mark.parametrize("key", ["cia402.node_id_1", "cia402.node_id_2"])
def test_a_drive_may_not_have_the_controllers_node_id(key):
    with pytest.raises(HalConfigError, match=rf"{key}: 127 is the controller's own node id"):
        RigConfig().with_overrides({key: CONTROLLER_NODE_ID})
    RigConfig().with_overrides({key: 126 if key.endswith("1") else 125})  # the rest is fine


def test_hil_cia402_check_refuses_it_in_one_line(tmp_path, capsys):
    conf = tmp_path / "id127.toml"
    conf.write_text("[cia402]\nnode_id_2 = 127\n")
    assert main(["cia402", "check", "--can", "virtual:nobody-127", "--config", str(conf)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cia402.node_id_2: 127 is the controller's" in err, err
