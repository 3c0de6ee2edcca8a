"""``hal.whole_file.written_whole``: the file asked for is replaced whole or not at all, and an
error names it, never the temporary file beside it."""

from __future__ import annotations

import errno
from pathlib import Path

import pytest

from hal.whole_file import partial_path, written_whole


def test_a_whole_write_replaces_the_file_and_leaves_nothing_beside_it(tmp_path: Path) -> None:
    path = tmp_path / "out.csv"
    path.write_text("old")
    with written_whole(path) as tmp:
        assert tmp.parent == tmp_path and tmp != path
        tmp.write_text("new")
        assert path.read_text() == "old"  # not before the block ends
    assert path.read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["out.csv"]


@pytest.mark.parametrize("failure", [KeyboardInterrupt, ValueError])
def test_a_failed_write_keeps_the_old_file(tmp_path: Path, failure: type) -> None:
    path = tmp_path / "out.csv"
    path.write_text("old")
    with pytest.raises(failure), written_whole(path) as tmp:
        tmp.write_text("half")
        raise failure()
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.csv"]


def test_a_full_disk_is_named_by_the_file_asked_for(tmp_path: Path) -> None:
    path = tmp_path / "out.csv"
    with pytest.raises(OSError) as info, written_whole(path) as tmp:
        tmp.write_text("half")
        raise OSError(errno.ENOSPC, f"No space left on device writing {tmp}")
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(path)
    assert str(info.value) == f"[Errno 28] No space left on device writing {path}: '{path}'"
    assert not path.exists() and list(tmp_path.iterdir()) == []


def test_a_library_error_type_is_kept(tmp_path: Path) -> None:
    class LibraryError(OSError):
        pass

    with pytest.raises(LibraryError), written_whole(tmp_path / "x") as tmp:
        tmp.write_text("half")
        raise LibraryError("its own words")
    assert list(tmp_path.iterdir()) == []


def test_a_link_is_followed_and_stays_a_link(tmp_path: Path) -> None:
    (tmp_path / "real").mkdir()
    target = tmp_path / "real" / "out.csv"
    target.write_text("old")
    link = tmp_path / "link.csv"
    link.symlink_to(target)
    with written_whole(link) as tmp:
        tmp.write_text("new")
    assert link.is_symlink() and target.read_text() == "new"


def test_a_missing_folder_is_named_by_the_file_asked_for(tmp_path: Path) -> None:
    path = tmp_path / "no-such-folder" / "out.csv"
    with pytest.raises(FileNotFoundError) as info, written_whole(path):
        pytest.fail("the block must not run")
    assert info.value.filename == str(path)


def test_a_killed_run_s_leftover_is_written_over(tmp_path: Path) -> None:
    path = tmp_path / "out.csv"
    tmp = partial_path(path)
    tmp.write_text("left by a killed run")
    with written_whole(path) as again:
        assert again == tmp
        again.write_text("new")
    assert path.read_text() == "new" and not tmp.exists()
