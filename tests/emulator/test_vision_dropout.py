"""The vision process's fault injection ``--dropout START:DURATION``: the camera publishes no
valid frame inside the window (lockstep: an invalid answer to every pose; realtime: nothing),
and the frame clock carries on after it."""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest

from hal.errors import HalConfigError
from hal.vision_codec import FeatureMsg, encode_features
from hal.vision_receivers import FeatureDecoder
from plant_emulator.vision_cli import main
from plant_emulator.vision_node import VisionCore
from plant_emulator.vision_timing import Dropout, in_dropout
from tests.support.poses import MS, PERIOD, camera_cfg, pose_msg

S = 1_000_000_000


def test_dropout_parses_start_and_duration_in_seconds():
    d = Dropout.parse(" 1.0:0.5 ")
    assert d == Dropout(1.0, 0.5) and str(d) == "1:0.5"
    assert (d.start_ns, d.end_ns) == (1 * S, 1500 * MS)
    assert not d.contains(S - 1) and d.contains(S) and d.contains(1500 * MS - 1)
    assert not d.contains(1500 * MS)  # the window is half-open
    assert in_dropout([Dropout(0, 0.1), d], 1200 * MS) and not in_dropout([d], 2 * S)
    assert not in_dropout([], 1200 * MS)


@pytest.mark.parametrize(
    "text", ["1.0", "a:0.5", "1:b", "-1:0.5", "1:0", "1:-0.5", "nan:1", "1:inf"]
)
def test_dropout_rejects_bad_windows_naming_the_option(text):
    with pytest.raises(HalConfigError, match="--dropout"):
        Dropout.parse(text)


def test_lockstep_dropout_answers_every_pose_invalid_and_features_go_stale(cfg):
    """Poses every 20 ms at 60 fps, dropout [1.0, 1.5) s: one answer per pose throughout; inside
    the window they are valid = 0 and the receiver keeps the last valid frame, whose sim-time age
    passes the controller's feature timeout; frames resume at the end of the window."""
    core = VisionCore(cfg, fps=60.0, dropouts=[Dropout(1.0, 0.5)])
    dec = FeatureDecoder(max_age_ns=None)
    timeout_ns = round(cfg.controller.feature_timeout_s * 1e9)
    answers, stale = [], []
    for k in range(100):  # 0 .. 1.98 s
        t = k * PERIOD
        out = core.on_pose(pose_msg(cfg, k, t, lockstep=True), 0)
        assert len(out) == 1 and out[0].pose_seq == k
        assert dec.feed(encode_features(out[0])) is not None  # ordered: never rejected
        answers.append(out[0])
        stale.append(dec.sim_age_ns(t) > timeout_ns)
    inside = [m for m in answers if 1 * S <= m.sim_time_ns < 1500 * MS]
    assert len(inside) == 25 and all(not m.valid and m.f == (0.0, 0.0) for m in inside)
    assert all(m.valid for m in answers if not 1 * S <= m.sim_time_ns < 1500 * MS)
    assert dec.counts.rejected == 0 and dec.counts.invalid == 25
    # the last valid frame before the window was taken at 0.98 s: stale from 1.1 s to 1.48 s
    stale_t = [k * PERIOD for k, s in enumerate(stale) if s]
    assert stale_t == [t * MS for t in range(1100, 1500, 20)]
    after = answers[75]  # 1.5 s: the frame slot at 1.5 s is captured again
    assert after.valid and after.sim_time_ns == 1500 * MS and after.frame > answers[49].frame
    st = core.stats
    assert st.answers == st.poses == 100 and st.dropout_answers == 25 and st.invalid == 25
    assert st.dropout_frames == 25 and st.dropouts == ["1:0.5"]  # slots due at 1.0 .. 1.48 s


def test_lockstep_dropout_discards_frames_due_inside_the_window(cfg):
    core = VisionCore(camera_cfg(cfg, latency_s=0.03), fps=0.0, dropouts=[Dropout(0.1, 0.1)])
    msgs = [core.on_pose(pose_msg(cfg, k, k * PERIOD, lockstep=True), 0)[0] for k in range(15)]
    # one frame per pose, delivered 30 ms later: the pose at 80 ms gets the frame of 40 ms
    assert [m.valid for m in msgs[:5]] == [False, False, True, True, True]
    assert msgs[4].sim_time_ns == 40 * MS
    # [100, 200) ms: nothing captured; the frames of 60 and 80 ms (due at 90 and 110 ms) fall
    # into the window and are discarded
    assert [m.valid for m in msgs[5:10]] == [False] * 5
    assert core.stats.dropout_discarded == 2 and core.stats.dropout_frames == 5
    # after the window the newest delivered frame (40 ms, far too old for the controller) is
    # re-sent until the frame captured at 200 ms is due at 230 ms
    assert [m.sim_time_ns for m in msgs[10:13]] == [40 * MS, 40 * MS, 200 * MS]
    assert all(m.valid for m in msgs[10:])
    assert [m.pose_seq for m in msgs] == list(range(15))


def test_realtime_dropout_publishes_nothing_inside_the_window(cfg):
    """Realtime at 1 kHz poses for 2 s of sim time: no message is captured or published while the
    (extrapolated) sim time is inside the window; the frame clock carries on afterwards."""
    core = VisionCore(cfg, fps=60.0, lockstep=False, dropouts=[Dropout(1.0, 0.5)])
    t0 = 7 * S
    published: list[FeatureMsg] = []
    for i in range(2000):
        now = t0 + i * MS
        published += core.on_pose(pose_msg(cfg, i, i * MS, lockstep=False), now)
        published += core.poll(now)
    sims = np.array([m.sim_time_ns for m in published])
    assert not np.any((sims >= 1 * S) & (sims < 1500 * MS))
    assert np.any(sims < 1 * S) and np.any(sims >= 1500 * MS)
    assert 28 <= core.stats.dropout_frames <= 31  # 0.5 s of 60 fps slots
    assert core.stats.frames == len(published)  # nothing captured was lost (no latency)
    assert [m.frame for m in published] == list(range(len(published)))
    assert all(m.valid for m in published)


def test_realtime_frames_follow_sparse_poses_and_skip_the_window(cfg):
    """Once the world runs, frames are taken at poses: a pose just before the window does not
    keep frames going, and a pose inside it is counted and not captured."""
    core = VisionCore(cfg, fps=100.0, lockstep=False, dropouts=[Dropout(1.0, 0.5)])
    t0 = 3 * S
    out = core.on_pose(pose_msg(cfg, 0, 990 * MS, lockstep=False), t0)
    out += [m for i in range(0, 400, 5) for m in core.poll(t0 + i * MS)]  # 0 .. 395 ms later
    assert [m.sim_time_ns for m in out] == [990 * MS]
    assert core.on_pose(pose_msg(cfg, 1, 1200 * MS, lockstep=False), t0 + 400 * MS) == []
    assert core.stats.dropout_frames == 1


def test_realtime_fps_zero_drops_poses_inside_the_window(cfg):
    core = VisionCore(cfg, fps=0.0, lockstep=False, dropouts=[Dropout(0.002, 0.002)])
    out = [core.on_pose(pose_msg(cfg, k, k * MS, lockstep=False), k * MS) for k in range(6)]
    assert [len(o) for o in out] == [1, 1, 0, 0, 1, 1]
    assert core.stats.dropout_frames == 2


def test_main_dropout_option(endpoint, capsys):
    rc = main(
        [
            *("--duration", "0.2", "--zenoh-endpoint", endpoint, "--zenoh-role", "hub", "--json"),
            *("--dropout", "1:0.5", "--dropout", "4:0.25"),
        ]
    )
    assert rc == 0
    out = capsys.readouterr()
    stats = json.loads(out.out.strip().splitlines()[-1])
    assert stats["dropouts"] == ["1:0.5", "4:0.25"] and stats["dropout_frames"] == 0
    assert "dropout 1:0.5, dropout 4:0.25" in out.err


@pytest.mark.parametrize("bad", ["0.5", "1:-2"])
def test_main_bad_dropout_is_one_clear_line(bad, capsys):
    assert main(["--dropout", bad, "--duration", "0.1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("hil vision: error: --dropout")


def test_hil_vision_cli_has_the_dropout_option():
    from rt_controller.cli import main as hil_main

    with pytest.raises(SystemExit) as exit_info, contextlib.redirect_stdout(io.StringIO()) as out:
        hil_main(["vision", "--help"])
    assert exit_info.value.code == 0 and "--dropout START:DURATION" in out.getvalue()
