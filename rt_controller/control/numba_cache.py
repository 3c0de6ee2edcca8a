"""numba's on-disk cache for the compiled kernels of this package, invalidated by the package.

numba keys a cached function on its own source file only: a kernel that calls a kernel of
another module, or reads a layout constant of :mod:`~rt_controller.control.state`, would keep
stale machine code when only that other file changed. For every ``cache=True`` function
defined under ``rt_controller/control/``, the cache's source stamp here also holds a digest of
all the package's Python sources, so a change to any of them recompiles them all (about a
minute, once) and the kernels can be split into modules by concern.

Import this module before any ``@njit(cache=True)`` of the package runs (each kernel module
imports it first): numba picks a function's cache locator when the function is decorated.
"""

from __future__ import annotations

import hashlib
from functools import cache
from pathlib import Path

from numba.core import caching

PACKAGE = Path(__file__).resolve().parent


@cache
def package_digest() -> str:
    """SHA-256 of the package's Python sources (names and contents, in path order)."""
    h = hashlib.sha256()
    for path in sorted(PACKAGE.rglob("*.py")):
        h.update(str(path.relative_to(PACKAGE)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def _in_package(py_file: str) -> bool:
    try:
        return Path(py_file).resolve().is_relative_to(PACKAGE)
    except OSError:
        return False


class _PackageStamp:
    """Mixin: the source stamp of a function of this package includes :func:`package_digest`."""

    def get_source_stamp(self):
        return (super().get_source_stamp(), package_digest())  # type: ignore[misc]

    @classmethod
    def from_function(cls, py_func, py_file):
        if not _in_package(py_file):
            return None
        return super().from_function(py_func, py_file)  # type: ignore[misc]


class PackageUserProvidedCacheLocator(_PackageStamp, caching.UserProvidedCacheLocator):
    """``NUMBA_CACHE_DIR`` set (a compile target's own cache)."""


class PackageInTreeCacheLocator(_PackageStamp, caching.InTreeCacheLocator):
    """The ``__pycache__`` beside the source."""


def install() -> None:
    """Put the package's locators before numba's own (once)."""
    classes = caching.CacheImpl._locator_classes
    for cls in (PackageInTreeCacheLocator, PackageUserProvidedCacheLocator):
        if cls not in classes:
            classes.insert(0, cls)


install()
