"""``hil controller``: the transport and clock options are configuration overrides, so the run
(its links, its log's ``hil.config``, its summary) reads them in one place, the config."""

from __future__ import annotations

import argparse
import threading

from hal.config import load_config
from rt_controller.commands import controller
from rt_controller.runtime.daemon import ControllerDaemon, DaemonOptions


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    controller.register(parser.add_subparsers())
    return parser.parse_args(["controller", *argv])


def test_the_command_lines_transports_and_clock_override_the_config():
    args = _args(
        "--can",
        "virtual:seam-test",
        "--clock",
        "lockstep",
        "--zenoh-endpoint",
        "tcp/127.0.0.1:7999",
        "--zenoh-config",
        "rig.json5",
    )
    cfg = controller.with_command_line(load_config(), args)
    assert cfg.controller.clock == "lockstep"
    assert cfg.transport.can == "virtual:seam-test"
    assert cfg.transport.zenoh_endpoint == "tcp/127.0.0.1:7999"
    assert cfg.transport.zenoh_config == "rig.json5"
    run = ControllerDaemon(cfg, controller.daemon_options(args), threading.Event()).what_runs()
    assert run["clock"] == "lockstep" and run["can"] == "virtual:seam-test"


def test_options_not_given_leave_the_config_alone():
    base = load_config().with_overrides({"controller.clock": "lockstep", "transport.can": "x:1"})
    cfg = controller.with_command_line(base, _args())
    assert cfg == base
    assert not {"can", "mode", "zenoh_endpoint", "zenoh_config"} & set(vars(DaemonOptions()))
