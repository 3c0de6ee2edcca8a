"""hil report of several logs: each log that cannot be read is named on stderr, also when none
of them can be read (not only the first)."""

from __future__ import annotations

import json

from rt_controller.cli import main


def test_every_unreadable_log_is_named_when_none_can_be_read(tmp_path, capsys):
    missing = tmp_path / "missing.mcap"
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    text = tmp_path / "notes.mcap"
    text.write_text("hello\n")
    assert main(["report", "-q", str(missing), str(empty), str(text)]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 3, err
    for path, line in zip((missing, empty, text), lines, strict=True):
        assert line.startswith(f"hil report: error: {path}: "), line


def test_json_of_several_logs_none_readable_prints_no_stray_stdout(tmp_path, capsys):
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    assert main(["report", "-q", "--json", str(tmp_path / "a.mcap"), str(empty)]) == 2
    out, err = capsys.readouterr()
    assert out == "" or isinstance(json.loads(out), list)
    assert len(err.strip().splitlines()) == 2, err


def test_plot_of_a_log_without_cycles_says_no_figure_was_written(tmp_path, capsys):
    """--plot on a log with nothing to draw (no cycle records): said, not silently nothing."""
    from hal.config import RigConfig
    from rt_controller.runtime.recorder import CycleRecorder

    log = tmp_path / "empty_run.mcap"
    CycleRecorder(log, RigConfig()).close()
    assert main(["report", "-q", "--plot", str(tmp_path / "figs"), str(log)]) == 0
    out = capsys.readouterr().out
    assert "plots: none" in out
    assert list((tmp_path / "figs").glob("*.png")) == []


def test_plots_of_logs_with_the_same_stem_do_not_overwrite_each_other(tmp_path, capsys):
    """a/run.mcap, b/run.mcap and run-2.mcap: three logs, three sets of figures."""
    from hal.config import RigConfig
    from rt_controller.runtime.recorder import CycleRecorder

    logs = [tmp_path / "a" / "run.mcap", tmp_path / "b" / "run.mcap", tmp_path / "run-2.mcap"]
    for log in logs:
        log.parent.mkdir(exist_ok=True)
        rec = CycleRecorder(log, RigConfig())
        for k in range(3):
            rec.record_cycle(
                {"tick": k, "t_ns": 10**9 + k, "sim_time_s": k * 0.02, "cycle_us": 1.0}
            )
        rec.close()
    figs = tmp_path / "figs"
    assert main(["report", "-q", "--json", "--plot", str(figs), *map(str, logs)]) == 0
    reports = json.loads(capsys.readouterr().out)
    plots = [set(r["plots"]) for r in reports]
    assert all(plots)
    assert not (plots[0] & plots[1]) and not (plots[1] & plots[2]) and not (plots[0] & plots[2])
