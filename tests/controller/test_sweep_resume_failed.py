"""A resume of a sweep folder that holds failed runs skips them (only ``--retry-failed``
runs them again), and its exit status says the study is not all good: 1, with one line
naming the failed runs and ``--retry-failed``. No cluster starts: every run is in the folder."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rt_controller.cli import main
from rt_controller.sweep.engines import base_row
from rt_controller.sweep.results import ResultStore
from rt_controller.sweep.spec import load_spec

SPEC = '[study]\nduration_s = 0.5\n\n[[axes]]\nkey = "plant.z_wo"\nvalues = [0.9, 1.1]\n'


def finished_folder(tmp_path: Path, failed: set[int]) -> tuple[Path, Path]:
    """A spec and its results folder where every run finished, those of ``failed`` failed."""
    spec_file = tmp_path / "study.toml"
    spec_file.write_text(SPEC)
    spec, out = load_spec(spec_file), tmp_path / "out"
    tasks = spec.tasks()
    with ResultStore(out, spec, tasks[0].engine) as store:
        for i, task in enumerate(tasks):
            store.add(base_row(task, "failed", "worker died") if i in failed else base_row(task))
    return spec_file, out


def test_a_resume_that_skips_failed_runs_exits_1_naming_them(tmp_path, capsys):
    spec_file, out = finished_folder(tmp_path, {1})
    code = main(["sweep", str(spec_file), "--out", str(out), "--no-progress", "--json"])
    captured = capsys.readouterr()
    assert code == 1, captured.err
    summary = json.loads(captured.out)
    assert summary["skipped"] == 2 and summary["ran"] == 0
    assert summary["kept_failed"] == ["point 1 rep 0"]
    line = captured.err.strip()
    assert "\n" not in line and "Traceback" not in line, line
    assert line.startswith("hil sweep: 1 failed run(s) in ")
    assert "point 1 rep 0" in line and "--retry-failed" in line


@pytest.mark.parametrize("failed", [set(), {0, 1}])
def test_a_resume_of_an_all_ok_folder_exits_0_and_failed_ones_1(tmp_path, capsys, failed):
    spec_file, out = finished_folder(tmp_path, failed)
    code = main(["sweep", str(spec_file), "--out", str(out), "--no-progress", "--json"])
    assert code == (1 if failed else 0), capsys.readouterr().err
