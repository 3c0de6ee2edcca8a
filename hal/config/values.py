"""The shapes a configuration value can have beyond a scalar: a 2-vector and a 2x2 matrix."""

from __future__ import annotations

Vec2 = tuple[float, float]
Mat2 = tuple[tuple[float, float], tuple[float, float]]


def diag(a: float, b: float) -> Mat2:
    """The 2x2 diagonal matrix diag(a, b) (a matrix key may be written as its diagonal)."""
    return ((a, 0.0), (0.0, b))
