"""``hil keygen`` writes a key only where a key file can be: never into a device, a FIFO or a
folder, and a replaced key (``--force``) is swapped in whole, so a full disk leaves the old
key as it was."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from hal.secoc import HalKeyError, load_key_file, write_key_file


@pytest.mark.parametrize("what", ["fifo", "folder"])
def test_a_target_that_is_not_a_regular_file_is_left_alone(tmp_path, what):
    target = tmp_path / "rig.key"
    if what == "fifo":
        os.mkfifo(target)
    else:
        target.mkdir()
    for overwrite in (False, True):
        with pytest.raises(HalKeyError, match="not a regular file; not replaced"):
            write_key_file(target, overwrite=overwrite)
    assert target.is_fifo() if what == "fifo" else target.is_dir()


def test_an_empty_path_is_refused():
    with pytest.raises(HalKeyError, match="the path is empty"):
        write_key_file("")


def fill_up(disk: Path) -> None:
    """Fill the file system of ``disk`` to its last block."""
    fd = os.open(disk / "filler", os.O_WRONLY | os.O_CREAT)
    try:
        while os.write(fd, b"\0" * 4096):
            pass
    except OSError:
        pass
    finally:
        os.close(fd)


def test_a_full_disk_keeps_the_key_being_replaced(tiny_tmpfs):
    key = write_key_file(tiny_tmpfs / "rig.key")
    before = load_key_file(key)
    fill_up(tiny_tmpfs)
    with pytest.raises(OSError, match="No space left on device") as info:
        write_key_file(key, overwrite=True)
    assert info.value.filename == str(key) and not isinstance(info.value, HalKeyError)
    assert load_key_file(key) == before
    assert sorted(p.name for p in tiny_tmpfs.iterdir()) == ["filler", "rig.key"]


def test_hil_keygen_onto_a_full_disk_fails_as_every_writer_does(tiny_tmpfs, capsys):
    """Exit 1 and ``PATH: No space left on device``, as ``hil camera calibrate --write`` or
    ``hil export`` on a full disk: a failed write, not a bad argument (exit 2)."""
    from rt_controller.cli import main

    fill_up(tiny_tmpfs)
    key = tiny_tmpfs / "rig.key"
    assert main(["keygen", str(key)]) == 1
    assert capsys.readouterr().err == f"hil keygen: error: {key}: No space left on device\n"
    assert not key.exists()
