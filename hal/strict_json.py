"""JSON as RFC 8259 defines it, for every ``--json`` line the commands print.

Python's :func:`json.dumps` writes ``NaN`` and ``Infinity`` for non-finite floats, which no
strict parser (``jq``, JavaScript, Go) accepts; a summary of a run that never ran the law has
such values (``f_final``). Here they are ``null``: no value.
"""

from __future__ import annotations

import json
import math
from typing import Any


def finite(obj: Any) -> Any:
    """``obj`` with every non-finite float (in dicts, lists, tuples, NumPy arrays and scalars,
    which become lists and Python numbers) replaced by None."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [finite(v) for v in obj]
    if type(obj).__module__ == "numpy" and hasattr(obj, "tolist"):  # NumPy is not imported
        return finite(obj.tolist())  # for this: --help stays light
    return obj


def dumps(obj: Any) -> str:
    """``obj`` as one line of strict JSON (non-finite floats as ``null``)."""
    return json.dumps(finite(obj), allow_nan=False)
