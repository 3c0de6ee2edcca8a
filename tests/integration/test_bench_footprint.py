"""``hil bench loop --json`` reports the footprint of every rig process at every rate.

Only the shape is checked (and one inequality that holds under any scheduling): sizes, CPU and
timings depend on the machine and are never asserted.
"""

from __future__ import annotations

import json

import pytest

from rt_controller.cli import main

pytestmark = [pytest.mark.integration, pytest.mark.slow]

PROCESS_KEYS = {
    "peak_rss_mb",
    "peak_rss_anon_mb",
    "peak_rss_file_mb",
    "peak_locked_mb",
    "vm_hwm_mb",
    "peak_threads",
    "cpu_percent",
    "cpu_window_s",
    "thread_cpu_percent",
}


def test_bench_loop_json_has_the_footprint_of_each_process(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code = main(
        ["bench", "loop", "--rates", "50", "--duration", "3", "--lockstep-duration", "0", "--json"]
    )
    assert code == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    (run,) = result["rates"]
    fp = run["footprint"]
    assert set(fp) == {"controller", "recorder", "emulator", "vision"}
    for role, figures in fp.items():
        assert set(figures) >= PROCESS_KEYS, role
        assert figures["peak_rss_mb"] > 0 and figures["peak_threads"] >= 1
    ctl = fp["controller"]
    assert {"spin_cpu_percent", "cpu_percent_excluding_spin"} <= set(ctl)
    # "touched" locks only resident pages, and locked pages stay resident.
    assert ctl["peak_locked_mb"] <= ctl["vm_hwm_mb"] + 1.0
