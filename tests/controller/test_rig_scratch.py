"""The run's private temporary folders (``rt_controller.rig.scratch``): a folder whose owner
process is gone is removed when the next folder of its prefix is made; one whose owner still
runs, or that names no owner, is kept."""

from __future__ import annotations

import os

from rt_controller.rig.scratch import OWNER_FILE, make_private_folder, private_folder, sweep
from tests.support.proc import folder_of_a_killed_run

PREFIX = "hil-scratch-test-"


def test_the_folder_of_a_killed_run_is_removed_by_the_next_run(tmp_path):
    left = folder_of_a_killed_run(PREFIX, tmp_path)
    (left / "rig.key").write_text("secret", encoding="ascii")
    mine = make_private_folder(PREFIX, tmp_path)
    assert not left.exists()
    assert mine.is_dir() and oct(mine.stat().st_mode & 0o777) == "0o700"
    assert sweep(PREFIX, tmp_path) == []  # its owner, this process, still runs


def test_a_reused_pid_is_not_taken_for_the_owner(tmp_path):
    """The owner's pid now belongs to another process (here: this one, started at another
    time than the stamp says): the folder is stale."""
    folder = tmp_path / f"{PREFIX}reused"
    folder.mkdir()
    (folder / OWNER_FILE).write_text(f"{os.getpid()} 1\n", encoding="ascii")
    assert sweep(PREFIX, tmp_path) == [folder] and not folder.exists()


def test_folders_that_name_no_owner_are_left_alone(tmp_path):
    bare = tmp_path / f"{PREFIX}bare"
    bare.mkdir()
    garbled = tmp_path / f"{PREFIX}garbled"
    garbled.mkdir()
    (garbled / OWNER_FILE).write_text("not a pid\n", encoding="ascii")
    plain_file = tmp_path / f"{PREFIX}file"
    plain_file.write_text("x", encoding="ascii")
    other = folder_of_a_killed_run("another-prefix-", tmp_path)
    link = tmp_path / f"{PREFIX}link"
    link.symlink_to(other)  # a stale folder, but not under this name
    assert sweep(PREFIX, tmp_path) == []
    assert bare.is_dir() and garbled.is_dir() and plain_file.is_file() and other.is_dir()


def test_the_context_removes_its_folder_on_any_exit():
    try:
        with private_folder(PREFIX) as folder:
            assert folder.is_dir()
            raise RuntimeError("the run failed")
    except RuntimeError:
        pass
    assert not folder.exists()
