"""Private temporary folders of a run, and the sweep of those that killed runs left behind.

A run removes its folders when it ends; one killed with SIGKILL cannot. Each folder made here
names its owner (pid and, on Linux, the process's start time, so a reused pid is not taken for
the owner), and making a folder first removes the folders of the same prefix whose owner is gone.
A folder without that name (made by another program, or by an older version) is left alone.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path

OWNER_FILE = ".owner"
"""The file in each folder that names its owner: ``"<pid> <start time>"``."""


def _start_time(pid: int) -> str:
    """The process's start time in clock ticks since boot (``/proc/PID/stat`` field 22), or ""
    where there is no ``/proc`` entry for it."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text(encoding="ascii")
    except OSError:
        return ""
    return stat.rsplit(")", 1)[1].split()[19]  # the fields after the name start at field 3


def _owner_alive(stamp: str) -> bool:
    pid_text, _, start = stamp.partition(" ")
    pid = int(pid_text)
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process has the pid: not our owner
        return False
    return not start or _start_time(pid) == start


def sweep(prefix: str, where: Path | None = None) -> list[Path]:
    """Remove this user's folders ``<where>/<prefix>*`` whose owner process is gone; the removed."""
    removed = []
    for folder in Path(where or tempfile.gettempdir()).glob(f"{prefix}*"):
        try:
            st = folder.lstat()  # a symlink is not a folder here
            if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid():
                continue
            stale = not _owner_alive((folder / OWNER_FILE).read_text(encoding="ascii").strip())
        except (OSError, ValueError):  # no owner named (or not readable): not ours to judge
            continue
        if stale:
            shutil.rmtree(folder, ignore_errors=True)
            removed.append(folder)
    return removed


def make_private_folder(prefix: str, where: Path | None = None) -> Path:
    """A new folder ``<prefix>XXXXXXXX`` (mode 0700) owned by this process, after the sweep of
    the stale ones of that prefix. The caller removes it."""
    sweep(prefix, where)
    folder = Path(tempfile.mkdtemp(prefix=prefix, dir=where))
    pid = os.getpid()
    (folder / OWNER_FILE).write_text(f"{pid} {_start_time(pid)}\n", encoding="ascii")
    return folder


@contextlib.contextmanager
def private_folder(prefix: str) -> Iterator[Path]:
    """:func:`make_private_folder` as a context: the folder is removed on leaving it."""
    folder = make_private_folder(prefix)
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)
