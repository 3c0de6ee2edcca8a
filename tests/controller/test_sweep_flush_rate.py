"""``results.parquet`` and ``results.csv`` are rewritten whole from the rows: when a rewrite
takes long (a big study), the store waits ``FLUSH_RATIO`` times as long before the next one,
so the sweep's client spends at most ~10% of its time rewriting; the final write
at the end still holds every row. On a fake clock: a rewrite "takes" 2 s, a run ends every 1 s."""

from __future__ import annotations

import types

import pyarrow.parquet as pq
import pytest

from rt_controller.sweep import results
from rt_controller.sweep.engines import base_row
from rt_controller.sweep.results import ResultStore
from rt_controller.sweep.spec import spec_from_dict

REWRITE_S, ARRIVAL_S, RUNS = 2.0, 1.0, 200
SHARE = 0.12  # of the time spent rewriting: ~1/FLUSH_RATIO, some slack


def test_slow_rewrites_are_spaced_and_the_end_writes_every_row(tmp_path, monkeypatch):
    now = [0.0]
    monkeypatch.setattr(results, "time", types.SimpleNamespace(monotonic=lambda: now[0]))
    rewrites = []
    write_table = pq.write_table

    def slow_write(table, path, *args, **kwargs):
        now[0] += REWRITE_S
        rewrites.append(table.num_rows)
        return write_table(table, path, *args, **kwargs)

    monkeypatch.setattr(pq, "write_table", slow_write)
    spec = spec_from_dict({"study": {"duration_s": 0.5, "repetitions": RUNS}})
    tasks = spec.tasks()
    with ResultStore(tmp_path, spec, tasks[0].engine) as store:
        for task in tasks:
            now[0] += ARRIVAL_S
            store.add(base_row(task))
        during = len(rewrites)
    assert during * REWRITE_S <= now[0] * SHARE + REWRITE_S, rewrites
    assert rewrites[-1] == RUNS and pq.read_table(tmp_path / "results.parquet").num_rows == RUNS
    assert (tmp_path / "results.csv").read_text().count("\n") == RUNS + 1


@pytest.mark.parametrize("runs", [1, 3])
def test_a_short_study_is_written_whole(tmp_path, runs):
    spec = spec_from_dict({"study": {"duration_s": 0.5, "repetitions": runs}})
    tasks = spec.tasks()
    with ResultStore(tmp_path, spec, tasks[0].engine) as store:
        for task in tasks:
            store.add(base_row(task))
    assert pq.read_table(tmp_path / "results.parquet").num_rows == runs
