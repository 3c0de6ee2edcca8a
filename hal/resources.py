"""Registry of open transport resources (buses, sessions) so leaks can be found.

Factories in :mod:`hal` register what they open; ``close()`` of a tracked object should call
:func:`release`. Tests use :func:`open_resources` to fail a test that leaks one.
"""

from __future__ import annotations

import threading
import weakref
from typing import Any

_lock = threading.Lock()
_open: weakref.WeakValueDictionary[int, Any] = weakref.WeakValueDictionary()
_labels: dict[int, str] = {}


def track(obj: Any, label: str) -> Any:
    """Remember ``obj`` as open; returns it for chaining."""
    with _lock:
        _open[id(obj)] = obj
        _labels[id(obj)] = label
    return obj


def release(obj: Any) -> None:
    """Forget ``obj`` (safe to call twice or for an untracked object)."""
    with _lock:
        _open.pop(id(obj), None)
        _labels.pop(id(obj), None)


def open_resources() -> list[str]:
    """Labels of tracked objects that are still alive and not released."""
    with _lock:
        return [_labels.get(key, "?") for key in list(_open.keys())]
