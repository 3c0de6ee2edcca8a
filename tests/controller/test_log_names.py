"""A run's default log name is its own: two controllers started in the same second (two rigs
on one host) never open one file, and an existing log is never reused."""

from __future__ import annotations

import threading

from hal.config import RigConfig
from rt_controller.runtime.daemon import ControllerDaemon, DaemonOptions, claim_log


def test_a_taken_name_gets_the_next_free_one(tmp_path):
    (tmp_path / "run-x.mcap").write_bytes(b"an earlier run")
    first, second = claim_log(tmp_path, "run-x"), claim_log(tmp_path, "run-x")
    assert (first.name, second.name) == ("run-x-2.mcap", "run-x-3.mcap")
    assert (tmp_path / "run-x.mcap").read_bytes() == b"an earlier run"


def test_two_daemons_of_one_second_log_to_two_files(tmp_path):
    cfg = RigConfig().with_overrides({"controller.log_dir": str(tmp_path)})
    stop = threading.Event()
    a = ControllerDaemon(cfg, DaemonOptions(), stop).log_path
    b = ControllerDaemon(cfg, DaemonOptions(), stop).log_path
    assert a != b and a.parent == b.parent == tmp_path
    assert a.exists() and b.exists()
