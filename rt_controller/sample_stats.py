"""The one percentile helper: summary statistics of timing samples (finite values only)."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

SUMMARY_KEYS = ("median", "p99", "max")


def finite(values: Iterable[float] | np.ndarray | None) -> np.ndarray:
    """The finite samples of ``values`` as a flat float array (empty for None)."""
    if values is None:
        return np.zeros(0)
    v = np.asarray(values, dtype=float).ravel()
    return v[np.isfinite(v)]


def percentile(values: Iterable[float] | np.ndarray | None, q: float) -> float:
    """The ``q``-th percentile of the finite samples; NaN when there are none."""
    v = finite(values)
    return float(np.percentile(v, q)) if v.size else math.nan


_STATS = {
    "min": lambda v: float(v.min()),
    "median": lambda v: float(np.median(v)),
    "p99": lambda v: float(np.percentile(v, 99)),
    "max": lambda v: float(v.max()),
    "mean": lambda v: float(v.mean()),
}


def summary_stats(
    values: Iterable[float] | np.ndarray | None, keys: Sequence[str] = SUMMARY_KEYS
) -> dict[str, float]:
    """``{key: statistic}`` of the finite samples (keys from min, median, p99, max, mean); NaN
    for every key when there are none."""
    v = finite(values)
    return {k: (_STATS[k](v) if v.size else math.nan) for k in keys}
