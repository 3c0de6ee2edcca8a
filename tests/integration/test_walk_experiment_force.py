"""``hil experiment --force`` into a folder holding an earlier experiment: the earlier run's
results, report and figures go before the new run starts, so a new run that is killed before
it writes its own leaves no earlier results to be read as its; files the experiment does not
write stay."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from tests.support.proc import reaped, wait_for

pytestmark = pytest.mark.integration

EARLIER = ("results.json", "report.md", "fig3_f.png", "fig3_xi.png", "fig3_u.png")


def test_force_drops_the_earlier_results_before_the_new_runs(tmp_path):
    out = tmp_path / "exp"
    (out / "logs").mkdir(parents=True)
    for name in EARLIER:
        (out / name).write_text("earlier experiment\n", encoding="utf-8")
    (out / "logs" / "ioc.mcap").write_text("earlier log\n", encoding="utf-8")
    mine = {out / "notes.txt": "mine\n", out / "logs" / "ioc.rerun.mcap": "a rerun\n"}
    for path, text in mine.items():
        path.write_text(text, encoding="utf-8")
    cmd = [sys.executable, "-m", "rt_controller.cli", "experiment", "fig3", "--out", str(out),
           "--force", "--duration", "600", "--jobs", "1", "-q"]  # fmt: skip
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True
    )
    with reaped(proc):  # killed before it writes its results: the rig's children go with it
        wait_for(lambda: (out / "configs" / "pbc.toml").exists(), "the runs' configs", proc)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
    left = [name for name in EARLIER if (out / name).exists()]
    assert left == [], f"the earlier experiment's {left} would read as this run's"
    log = out / "logs" / "ioc.mcap"
    assert not log.exists() or log.read_bytes() != b"earlier log\n"
    for path, text in mine.items():  # not the experiment's: kept
        assert path.read_text(encoding="utf-8") == text
