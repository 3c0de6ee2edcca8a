"""Run-long timing statistics in fixed memory: an HdrHistogram of durations.

A process that runs for hours (the soak, a lab's day) cannot keep every per-frame or per-tick
sample for its summary's percentiles: memory would grow with the run. An HdrHistogram keeps
counts in buckets of 0.1 % relative width, so the median and p99 it gives are within 0.1 % of
the samples' own, in about 100 KB however long the run.
"""

from __future__ import annotations

from hdrh.histogram import HdrHistogram

LOWEST_NS = 1_000
"""Values are told apart from 1 us up; shorter ones share the lowest buckets."""
HIGHEST_NS = 60_000_000_000
"""Longer durations (60 s) are recorded as 60 s and counted in :attr:`Durations.clipped`."""
SIGNIFICANT_DIGITS = 3


class Durations:
    """Durations in ns (negative ones, from clocks of two hosts, are recorded as 0 and counted
    in :attr:`clipped` with the over-long ones). A percentile is held within the samples'
    exact minimum and maximum: a bucket's top is no figure of a run that never reached it (a
    lockstep run's lateness, 0 every tick, reads 0, not the 0.511 us of the lowest bucket)."""

    def __init__(self) -> None:
        self._hist = HdrHistogram(LOWEST_NS, HIGHEST_NS, SIGNIFICANT_DIGITS)
        self.clipped = 0
        self._min = HIGHEST_NS
        self._max = 0

    def add(self, ns: int) -> None:
        ns = int(ns)
        if ns < 0 or ns > HIGHEST_NS:
            self.clipped += 1
            ns = min(max(ns, 0), HIGHEST_NS)
        self._hist.record_value(ns)
        self._min, self._max = min(self._min, ns), max(self._max, ns)

    def __len__(self) -> int:
        return self._hist.get_total_count()

    def percentile_us(self, q: float) -> float:
        """The ``q``-th percentile in us (0.0 when empty)."""
        if not len(self):
            return 0.0
        return min(max(self._hist.get_value_at_percentile(q), self._min), self._max) / 1e3

    def percentiles_us(self) -> tuple[float, float]:
        """Median and p99 in us."""
        return self.percentile_us(50), self.percentile_us(99)
