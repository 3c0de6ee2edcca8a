"""``hil sweep`` and ``hil export`` off their paths, without a Dask cluster: specs that look
valid but are not, a results folder that is not a sweep's, the report of an interrupted sweep,
and export files that cannot be written."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from hal.config import RigConfig
from plant_emulator.world import World
from rt_controller.cli import main
from rt_controller.errors import ControllerConfigError
from rt_controller.sweep.engines import run_task
from rt_controller.sweep.report import write_report
from rt_controller.sweep.results import ResultStore
from rt_controller.sweep.spec import SweepSpecError, spec_from_dict
from tests.controller.test_logs import record

AXIS = {"key": "plant.z_wo", "values": [0.9, 1.1]}


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    return err


@pytest.mark.parametrize("values", [[1, 1.0], [50, 50.0, 60]])
def test_numbers_equal_as_config_values_are_one_point(values):
    """``1`` and ``1.0`` are the same setting: two points of one config, counted twice."""
    with pytest.raises(SweepSpecError, match="a value is listed twice"):
        spec_from_dict({"axes": [{"key": "rates.control_hz", "values": values}]})


def test_a_toml_date_as_an_axis_value_is_one_line_and_exit_2(tmp_path, capsys):
    spec = tmp_path / "date.toml"
    spec.write_text('[[axes]]\nkey = "plant.z_wo"\nvalues = [1979-05-27]\n')
    assert main(["sweep", str(spec), "--out", str(tmp_path / "out")]) == 2
    err = one_line_error(capsys)
    assert err.startswith("hil sweep: error: ") and "is not a number, string" in err
    assert not (tmp_path / "out").exists()


def test_repetitions_reuse_their_point_config(monkeypatch):
    """A point's config is built and validated once, not once per repetition (a 1000-run
    spec of 2 points no longer builds 1000 configs); each run's config is the point's with its
    own seed, as ``camera.seed`` would set it."""
    spec = spec_from_dict({"study": {"repetitions": 40}, "axes": [AXIS]})
    built = []
    original = RigConfig.with_overrides

    def counting(self, overrides):
        built.append(dict(overrides))
        return original(self, overrides)

    monkeypatch.setattr(RigConfig, "with_overrides", counting)
    tasks = spec.tasks()
    assert len(tasks) == 80 and len(built) <= 2, built[:4]
    monkeypatch.setattr(RigConfig, "with_overrides", original)
    for task in (tasks[0], tasks[41]):
        point = spec.base.with_overrides(task.axes)
        assert task.config == point.with_overrides({"camera.seed": task.seed}).to_dict()


@pytest.mark.parametrize("name", ["report.md", "results.csv"])
def test_a_folder_with_someone_elses_files_is_refused(tmp_path, name):
    mine = tmp_path / name
    mine.write_text("my own notes\n")
    with pytest.raises(ControllerConfigError, match=f"has {name} but no sweep.json"):
        ResultStore(tmp_path, spec_from_dict({"axes": [AXIS]}))
    assert mine.read_text() == "my own notes\n"


def test_the_report_of_an_interrupted_sweep_names_what_did_not_run(tmp_path):
    axis = {**AXIS, "values": [0.9, 1.0, 1.1]}
    spec = spec_from_dict({"study": {"duration_s": 0.5, "repetitions": 2}, "axes": [axis]})
    tasks = spec.tasks()
    with ResultStore(tmp_path, spec) as store:
        for task in tasks[:3]:  # point 0 whole, point 1 half: then Ctrl-C
            store.add(run_task(task, World))
    report = write_report(tmp_path, spec).read_text()
    assert "- runs: 3 of 6 finished" in report
    assert "not finished: 3 run(s)**, at 2 point(s)" in report
    table = [line for line in report.splitlines() if line.startswith("| ")]
    assert [line.split(" | ")[:3] for line in table[1:]] == [
        ["| 0.9", "2", "2"],
        ["| 1", "2", "1"],
        ["| 1.1", "2", "0"],  # a point with no finished run is still a line of the table
    ]


@pytest.mark.parametrize(
    ("spec_text", "extra"),
    [
        ('[[axes]]\nkey = "plant.z_wo"\nvalues = [1.0]\n', ["--workers", "2", "--scheduler",
                                                           "tcp://127.0.0.1:1"]),
        ('[base.hardware]\nprofile = "cia402"\n', []),  # the simulate engine refuses it
    ],
)  # fmt: skip
def test_bad_options_or_engine_are_refused_before_the_folder_is_made(
    tmp_path, capsys, spec_text, extra
):
    spec = tmp_path / "s.toml"
    spec.write_text(spec_text)
    out = tmp_path / "out"
    assert main(["sweep", str(spec), "--out", str(out), "--no-progress", *extra]) == 2
    assert one_line_error(capsys).startswith("hil sweep: error: ")
    assert not out.exists()


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    return record(tmp_path_factory.mktemp("walk") / "run.mcap", ticks=20)


@pytest.mark.parametrize(("fmt", "topics"), [("mat", "cycle,can"), ("csv", "cycle")])
def test_an_export_file_that_cannot_be_opened_is_named_with_the_reason(
    log, tmp_path, capsys, fmt, topics
):
    """The file exists as a link to nowhere (as a read-only file would fail for a user):
    the line names the file and the OS's reason, not scipy's 'Reader needs file name'."""
    link = tmp_path / f"out.{fmt}"
    link.symlink_to(tmp_path / "no-such-dir" / f"x.{fmt}")
    argv = ["export", str(log), "--format", fmt, "--topics", topics, "--out", str(link)]
    assert main(argv) == 2
    err = one_line_error(capsys)
    assert f"out.{fmt}: No such file or directory" in err, err


def test_an_export_beside_the_log_does_not_name_an_out_not_given(log, capsys):
    """No --out: the files go beside LOG; a folder that takes no file is named as such."""
    with log.open("rb") as fh:  # a log whose folder takes no new file, root or not
        beside = f"/proc/self/fd/{fh.fileno()}"
        assert main(["export", beside, "--format", "csv", "--topics", "cycle"]) == 2
    err = one_line_error(capsys)
    assert "cannot write into it" in err and "--out" not in err, err
    assert os.path.exists(log)


def test_bench_sweep_names_its_own_option_for_a_duration_a_sweep_refuses(capsys):
    """4000 s passes the option's own range but not a study's (duration_s up to 3600)."""
    argv = ["bench", "sweep", "--runs", "1", "--duration", "4000", "--rig-runs", "0", "-q"]
    assert main(argv) == 2
    err = one_line_error(capsys)
    assert "--duration 4000" in err and "out of range" in err, err
