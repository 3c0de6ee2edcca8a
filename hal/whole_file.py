"""A file written beside its final name and renamed onto it only when whole.

Every tool that writes a user's file (a recovered log, an export, a replayed log, a plot, the
rig config, a key) writes through :func:`written_whole`: a full disk, an error or an interrupt
leaves the previous file as it was and no half file, and the error names the file asked for,
never the temporary one.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path


def partial_path(path: Path) -> Path:
    """The temporary name beside ``path`` (its link target's, for a symbolic link)."""
    target = Path(os.path.realpath(path))
    return target.with_name(f".{target.name}.partial")


def _named(exc: OSError, tmp: Path, path: Path) -> OSError:
    """A built-in ``exc`` naming ``path`` where it named ``tmp`` or nothing (a full disk);
    a library's own error type is kept as it is."""
    if type(exc).__module__ != "builtins" or exc.filename not in (None, str(tmp), tmp):
        return exc
    text = " ".join((exc.strerror or str(exc)).split()).replace(str(tmp), str(path))
    return OSError(exc.errno, text, str(path))


@contextlib.contextmanager
def written_whole(path: str | Path) -> Iterator[Path]:
    """Yield the temporary path to write; on a normal exit rename it onto ``path``.

    On any exception the temporary file is deleted and ``path`` is untouched; a built-in
    :class:`OSError` is re-raised naming ``path`` (``filename``) with the temporary name
    replaced in its text. A link is followed: its target is replaced, the link stays.
    """
    path = Path(path)
    tmp = partial_path(path)
    try:
        if not tmp.parent.is_dir():  # a link to nowhere, or a missing folder
            raise FileNotFoundError(2, os.strerror(2), str(path))
        yield tmp
        os.replace(tmp, tmp.with_name(tmp.name[1 : -len(".partial")]))
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise _named(exc, tmp, path) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
