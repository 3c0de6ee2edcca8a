"""The shapes a configuration value can have beyond a scalar: a 2-vector and a 2x2 matrix."""

from __future__ import annotations

Vec2 = tuple[float, float]
Mat2 = tuple[tuple[float, float], tuple[float, float]]


def diag(a: float, b: float) -> Mat2:
    """The 2x2 diagonal matrix diag(a, b) (a matrix key may be written as its diagonal)."""
    return ((a, 0.0), (0.0, b))


LONGEST_INT_SHOWN = 30
"""Digits of the longest integer an error message repeats (a longer one is described)."""


def shown(value: object) -> str:
    """``value`` as an error message repeats what the file said: TOML's ``true``/``false``,
    a date or time as written, a list in brackets, an integer of more than
    :data:`LONGEST_INT_SHOWN` digits by its length (a 400-digit literal is valid TOML); any
    other value (a string, a float) as Python's ``repr``."""
    import datetime

    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        digits = len(str(abs(value)))
        return str(value) if digits <= LONGEST_INT_SHOWN else f"an integer of {digits} digits"
    if isinstance(value, datetime.date | datetime.time):
        return value.isoformat()
    if isinstance(value, list | tuple):
        return "[" + ", ".join(shown(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {shown(v)}" for k, v in value.items()) + "}"
    return repr(value)
