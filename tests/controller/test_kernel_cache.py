"""A rig compiles its kernels once per process before its children start (rig.kernel_cache)."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from rt_controller.rig.failures import RigCancelled
from rt_controller.rig.kernel_cache import prepare_kernels


def test_the_kernels_of_one_configuration_are_prepared_once_per_process(tmp_path: Path):
    config = tmp_path / "rig.toml"
    config.write_text("")  # the embedded defaults, under a name no other test uses
    assert prepare_kernels(str(config), "ioc") is True
    assert prepare_kernels(str(config), "ioc") is False


def test_a_configuration_that_does_not_load_is_left_to_the_children(tmp_path: Path):
    config = tmp_path / "bad.toml"
    config.write_text("[controller]\nlaw = 'no such law'\n")
    assert prepare_kernels(str(config), None) is True
    assert prepare_kernels(str(config), None) is True  # not remembered: it never compiled


def test_a_cancelled_rig_stops_compiling(tmp_path: Path):
    cancel = threading.Event()
    cancel.set()
    with pytest.raises(RigCancelled):
        prepare_kernels(str(tmp_path / "cancelled.toml"), "rhc", cancel)
