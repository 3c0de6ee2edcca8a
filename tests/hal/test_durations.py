"""Run-long duration statistics: HdrHistogram's percentiles against the samples' own."""

import tracemalloc

import numpy as np
import pytest

from hal.durations import HIGHEST_NS, Durations


def test_percentiles_within_a_tenth_of_a_percent_of_the_samples():
    rng = np.random.default_rng(7)
    samples = rng.lognormal(13.5, 0.6, 20_000).astype(np.int64)  # ~0.7 ms, a detector's spread
    d = Durations()
    for ns in samples:
        d.add(int(ns))
    p50, p99 = d.percentiles_us()
    assert len(d) == samples.size and d.clipped == 0
    assert p50 == pytest.approx(np.percentile(samples, 50) / 1e3, rel=2e-3)
    assert p99 == pytest.approx(np.percentile(samples, 99) / 1e3, rel=2e-3)


def test_memory_does_not_grow_with_the_run():
    d = Durations()
    d.add(1_000)
    tracemalloc.start()
    try:
        before, _ = tracemalloc.get_traced_memory()
        for i in range(100_000):  # half an hour of 60 fps; as samples: 800 KB at 8 B each
            d.add(1_000 + i)
        after, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(d) == 100_001
    assert after - before < 10_000


def test_empty_and_out_of_range():
    d = Durations()
    assert len(d) == 0 and d.percentiles_us() == (0.0, 0.0)
    d.add(-5)
    d.add(HIGHEST_NS * 2)
    assert d.clipped == 2 and len(d) == 2
    assert d.percentile_us(100) == pytest.approx(HIGHEST_NS / 1e3, rel=2e-3)


def test_a_run_of_zeros_reads_zero_not_its_buckets_top():
    """A lockstep run's lateness is 0 every tick: its median and p99 are 0, not the 0.511 us
    at the top of the lowest bucket (values under 1 us share it)."""
    d = Durations()
    for _ in range(100):
        d.add(0)
    assert d.percentiles_us() == (0.0, 0.0)


def test_a_percentile_stays_within_the_samples():
    d = Durations()
    for ns in (1_234_567, 1_234_999, 2_000_001):
        d.add(ns)
    p50, p99 = d.percentiles_us()
    assert p50 >= 1234.567 and p99 <= 2000.001
