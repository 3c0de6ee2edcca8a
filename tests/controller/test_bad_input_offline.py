"""Offline commands given a user's mistakes: one line naming the bad input, exit 2, no
traceback, no file touched, and the same shape of output whatever failed."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from rt_controller.cli import main
from rt_controller.runtime.recorder import CycleRecorder


def test_calibrate_into_a_file_that_is_not_utf8_is_refused_untouched(tmp_path: Path, capsys):
    target = tmp_path / "rig.toml"
    target.write_bytes(b"\xff\xfe[gains]\n")
    argv = ["camera", "calibrate", "--source", "emulated", "--views", "6", "--write", str(target)]
    status = main(argv)
    last = capsys.readouterr().err.splitlines()[-1]  # (after a note on the few views' fit)
    assert status == 2 and last.startswith("hil camera calibrate: error: ")
    assert "not UTF-8 text" in last and str(target) in last
    assert target.read_bytes() == b"\xff\xfe[gains]\n"


def test_images_of_another_size_are_named_by_file(tmp_path: Path, capsys):
    import cv2

    cv2.imwrite(str(tmp_path / "a.png"), np.full((48, 64), 200, np.uint8))
    cv2.imwrite(str(tmp_path / "b.png"), np.full((40, 64), 200, np.uint8))
    status = main(["camera", "calibrate", "--images", str(tmp_path)])
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1
    assert str(tmp_path / "b.png") in err and "64x40" in err and "64x48" in err


def test_param_load_names_a_missing_file_before_looking_for_the_rig(tmp_path: Path, capsys):
    missing = tmp_path / "tuned.toml"
    argv = ["param", "--timeout", "0.2", "--zenoh-endpoint", "tcp/127.0.0.1:1"]
    for action in ("load", "diff"):
        assert main([*argv, action, str(missing)]) == 2
        err = capsys.readouterr().err
        assert "cannot read config file" in err and str(missing) in err and "hub" not in err


def test_report_json_of_several_logs_is_a_list_even_when_one_is_bad(tmp_path: Path, cfg, capsys):
    good = tmp_path / "good.mcap"
    with CycleRecorder(good, cfg, run_info={"law": "ioc"}) as rec:
        for i in range(3):
            rec.record_cycle({"tick": i, "t_ns": i * 20_000_000, "law": "ioc"})
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not a log")
    assert main(["report", "--json", "-q", str(good), str(bad)]) == 2
    out = capsys.readouterr()
    rows = json.loads(out.out)
    assert isinstance(rows, list) and [r["log"] for r in rows] == [str(good)]
    assert "bad.mcap" in out.err


def test_a_pipe_given_as_the_log_is_named_as_such(capsys):
    import os

    read_end, write_end = os.pipe()  # `hil info <(cat run.mcap)`, or a FIFO (would block)
    os.write(write_end, b"\x89MCAP0\r\n" + b"\x00" * 64)
    os.close(write_end)
    try:
        assert main(["info", f"/proc/self/fd/{read_end}"]) == 2
    finally:
        os.close(read_end)
    err = capsys.readouterr().err
    assert "not a regular file" in err and "cut short" not in err and err.count("\n") == 1


def big_log(path: Path, cfg) -> Path:
    """A log larger than :func:`tiny_tmpfs` holds (its numbers are incompressible)."""
    with CycleRecorder(path, cfg, run_info={"law": "ioc"}, chunk_size=4096) as rec:
        noise = np.random.default_rng(0).random((6000, 8)).tolist()
        for i, q in enumerate(noise):
            rec.record_cycle(
                {"tick": i, "t_ns": i * 20_000_000, "law": "ioc", "q": q[:2], "f": q[2:4]}
                | {"lateness_us": q[4], "cycle_us": 100 * q[5], "tau": q[6:], "u": q[6:]}
            )
    assert path.stat().st_size > 2 * 192 * 1024
    return path


def test_recover_onto_a_full_disk_names_the_copy_and_leaves_nothing(
    tmp_path: Path, cfg, tiny_tmpfs: Path, capsys
):
    log = big_log(tmp_path / "cut.mcap", cfg)
    out = tiny_tmpfs / "copy.mcap"
    assert main(["recover", "--out", str(out), str(log)]) == 1
    err = capsys.readouterr().err
    assert err == f"hil recover: error: {out}: No space left on device\n"
    assert list(tiny_tmpfs.iterdir()) == []


def test_export_onto_a_full_disk_keeps_the_previous_export(
    tmp_path: Path, cfg, tiny_tmpfs: Path, capsys
):
    log = big_log(tmp_path / "run.mcap", cfg)
    out = tiny_tmpfs / "run.mat"
    out.write_bytes(b"the export of yesterday")
    assert main(["export", "--format", "mat", "--topics", "cycle", "--out", str(out), str(log)])
    err = capsys.readouterr().err
    assert str(out) in err and "No space left on device" in err and err.count("\n") == 1
    assert out.read_bytes() == b"the export of yesterday"
    assert [p.name for p in tiny_tmpfs.iterdir()] == ["run.mat"]


def test_report_plots_onto_a_full_disk_name_the_figure_and_leave_no_half_png(
    tmp_path: Path, cfg, tiny_tmpfs: Path, capsys
):
    import os

    log = big_log(tmp_path / "run.mcap", cfg)
    room = os.statvfs(tiny_tmpfs)
    (tiny_tmpfs / "filler").write_bytes(b"x" * (room.f_bavail * room.f_frsize - 2_000))
    plots = tiny_tmpfs / "plots"
    assert main(["report", "-q", "--plot", str(plots), str(log)]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"hil report: error: {plots}/run_") and err.count("\n") == 1
    assert err.endswith(".png: No space left on device\n")
    for png in plots.iterdir():  # the figures that fitted are whole
        assert png.read_bytes().endswith(b"IEND\xaeB`\x82")


def test_report_plots_onto_a_full_disk_keep_the_last_figures(
    tmp_path: Path, cfg, tiny_tmpfs: Path, capsys
):
    import os

    log = big_log(tmp_path / "run.mcap", cfg)
    assert main(["report", "-q", "--plot", str(tmp_path / "first"), str(log)]) == 0
    plots = tiny_tmpfs / "plots"
    plots.mkdir()
    names = sorted(p.name for p in (tmp_path / "first").iterdir())
    for name in names:  # the last report's figures, small
        (plots / name).write_bytes(b"yesterday's figure")
    room = os.statvfs(tiny_tmpfs)
    (tiny_tmpfs / "filler").write_bytes(b"x" * (room.f_bavail * room.f_frsize - 2_000))
    assert main(["report", "-q", "--plot", str(plots), str(log)]) == 1
    assert "No space left on device" in capsys.readouterr().err
    assert sorted(p.name for p in plots.iterdir()) == names  # nothing lost, nothing half
    kept = [p.read_bytes() for p in plots.iterdir()]
    assert b"yesterday's figure" in kept
    assert all(b == b"yesterday's figure" or b.endswith(b"IEND\xaeB`\x82") for b in kept)


def test_a_log_cut_by_a_full_disk_is_said_so(tmp_path: Path, cfg, tiny_tmpfs: Path, capsys):
    log = tiny_tmpfs / "run.mcap"
    rec = CycleRecorder(log, cfg, run_info={"law": "ioc"}, chunk_size=4096)
    for i, q in enumerate(np.random.default_rng(0).random((6000, 8)).tolist()):
        if not rec.record_cycle({"tick": i, "t_ns": i * 20_000_000, "law": "ioc", "q": q[:2]}):
            break
    rec.close()
    assert "No space left on device" in str(rec.error)
    main(["info", str(log)])
    out = capsys.readouterr().out
    assert "killed or crashed" not in out
    assert "the disk probably filled up while recording" in out
