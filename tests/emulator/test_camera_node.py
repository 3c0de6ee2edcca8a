"""The emulated network camera: one frame per lockstep period, its own frame clock in realtime,
bit-exact for a seed, restarts with a scenario reset."""

from __future__ import annotations

import numpy as np

from hal.camera_frame import decode_frame
from hal.config import RigConfig
from plant_emulator.camera import CameraPose, camera_pose
from plant_emulator.camera_node import CameraNode

KEY = b"c" * 32
PERIOD_NS = 20_000_000


class FakeClock:
    def __init__(self) -> None:
        self.now = 1_000_000_000

    def __call__(self) -> int:
        return self.now


def moving_pose(cfg: RigConfig, t: float) -> CameraPose:
    q = np.array(cfg.scenario.q0) + np.array([0.3, -0.2]) * t
    return camera_pose(cfg.robot, q)


def lockstep_run(seed: int, periods: int = 6, resend: int | None = None):
    cfg = RigConfig().with_overrides({"camera.seed": seed})
    out: list[bytes] = []
    node = CameraNode(cfg, out.append, key=KEY, clock=FakeClock())
    for k in range(periods):
        sim = k * PERIOD_NS
        node.offer(k, sim, moving_pose(cfg, sim * 1e-9), True)
        node.drain()
        if k == resend:
            node.offer(k, sim, moving_pose(cfg, sim * 1e-9), True)
            node.drain()
    return node, out


def test_lockstep_gives_one_frame_per_period_stamped_mid_exposure():
    node, out = lockstep_run(seed=3)
    frames = [decode_frame(b) for b in out]
    assert [f.period for f in frames] == list(range(6))
    assert [f.seq for f in frames] == list(range(6))
    assert all(f.lockstep for f in frames)
    exposure = node.exposure_ns
    assert exposure == 4_000_000
    assert [f.sim_time_ns for f in frames] == [k * PERIOD_NS - exposure // 2 for k in range(6)]
    assert node.stats.frames == 6 and node.stats.resent == 0


def test_lockstep_is_bit_exact_for_a_seed_and_differs_across_seeds():
    _, a = lockstep_run(seed=3)
    _, b = lockstep_run(seed=3)
    _, c = lockstep_run(seed=4)
    pa = [decode_frame(x).pixels for x in a]
    for x, y in zip(pa, [decode_frame(x).pixels for x in b], strict=True):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(pa[-1], decode_frame(c[-1]).pixels)


def test_a_resent_pose_gets_the_same_frame_again():
    node, out = lockstep_run(seed=3, resend=2)
    assert len(out) == 7 and out[2] == out[3]
    assert node.stats.resent == 1 and node.stats.frames == 6
    assert decode_frame(out[4]).period == 3


def test_realtime_frames_come_on_the_cameras_clock_from_interpolated_poses():
    cfg = RigConfig().with_overrides({"camera.frame_rate_hz": 50.0})
    clock = FakeClock()
    out: list[bytes] = []
    node = CameraNode(cfg, out.append, key=KEY, clock=clock)
    for step in range(1, 201):  # 200 ms of poses at 1 kHz
        sim = step * 1_000_000
        clock.now += 1_000_000
        node.offer(step, sim, moving_pose(cfg, sim * 1e-9), False)
        if step % 3 == 0:  # the renderer wakes now and then, poses pile up meanwhile
            node.drain()
    node.drain()
    frames = [decode_frame(b) for b in out]
    # slots at 0, 20, ..., 180 ms of sim time (200 ms: its exposure has not ended)
    assert [f.sim_time_ns for f in frames] == [j * 20_000_000 for j in range(10)]
    assert not any(f.lockstep for f in frames)
    # capture stamps: the monotonic time of the mid-exposure pose
    assert frames[1].stamp_ns == 1_000_000_000 + 20_000_000
    assert node.stats.skipped == 0


def test_realtime_skips_slots_it_could_not_keep_up_with():
    cfg = RigConfig().with_overrides({"camera.frame_rate_hz": 100.0})
    out: list[bytes] = []
    node = CameraNode(cfg, out.append, key=KEY, clock=FakeClock())
    for step in range(1, 101):
        node.offer(step, step * 1_000_000, moving_pose(cfg, step * 1e-3), False)
    node.drain()  # one wake after 100 ms: only the newest due slot is rendered
    frames = [decode_frame(b) for b in out]
    assert [f.sim_time_ns for f in frames] == [90_000_000]
    assert node.stats.skipped == 9


def test_a_scenario_reset_restarts_the_frame_counter_with_the_named_seed():
    cfg = RigConfig()
    out: list[bytes] = []
    node = CameraNode(cfg, out.append, key=KEY, clock=FakeClock())
    for k in range(3):
        node.offer(k, k * PERIOD_NS, moving_pose(cfg, k * 0.02), True)
    node.new_run(99)
    for k in range(3):
        node.offer(k, k * PERIOD_NS, moving_pose(cfg, k * 0.02), True)
    node.drain()
    frames = [decode_frame(b) for b in out]
    assert [f.seq for f in frames] == [0, 1, 2, 0, 1, 2]
    assert node.stats.runs == 2
    assert not np.array_equal(frames[2].pixels, frames[5].pixels)
    reseeded, _ = lockstep_run(seed=99, periods=3)
    assert reseeded.sensor.seed == 99 == node.sensor.seed


def test_frames_reach_a_frame_grabber_over_zenoh_authenticated():
    """The camera on the hub's session, a grabber on a client: every lockstep frame arrives,
    in order, authenticated with the rig key, and a grabber with another key rejects them."""
    import threading

    from hal.camera_frame import FrameDecoder
    from hal.zenoh_session import KEY_CAMERA_FRAME, free_loopback_port, open_session
    from plant_emulator.camera_node import FramePublisher
    from plant_emulator.pose_link import wait_until

    cfg = RigConfig()
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    got: list[int] = []
    arrived = threading.Condition()
    grabber = FrameDecoder(key=KEY)
    stranger = FrameDecoder(key=b"x" * 32)

    def on_frame(payload: bytes) -> None:
        stranger.feed(payload)
        frame = grabber.feed(payload)
        with arrived:
            if frame is not None:
                got.append(frame.period)
            arrived.notify_all()

    with (
        open_session(listen=True, endpoint=endpoint) as hub,
        open_session(listen=False, endpoint=endpoint) as client,
    ):
        frames = FramePublisher(hub)
        client.subscribe(KEY_CAMERA_FRAME, on_frame)
        assert wait_until(frames.has_subscribers, 10.0)
        node = CameraNode(cfg, frames.put, key=KEY).start()
        try:
            for k in range(20):
                node.offer(k, k * PERIOD_NS, moving_pose(cfg, k * 0.02), True)
                with arrived:
                    assert arrived.wait_for(lambda k=k: len(got) > k, 10.0)
        finally:
            node.close()
            frames.close()
    assert got == list(range(20))
    assert grabber.counters()["rejected"] == 0
    assert stranger.counters()["bad_mac"] == 20
    assert node.stats.publish_errors == 0


def test_a_frame_that_cannot_be_made_is_counted_and_the_camera_goes_on(capsys):
    """A scene that fails for one frame: that frame is lost (counted, one line on stderr), the
    worker keeps answering the next periods."""
    import time

    from plant_emulator.camera_node import target_scene

    cfg = RigConfig()
    good = target_scene(cfg)
    bad_time = 2 * PERIOD_NS * 1e-9

    def scene(t: float):
        if abs(t - bad_time) < 0.003:
            raise ValueError("texture unavailable")
        return good(t)

    from plant_emulator.camera_node import sensor_from_config

    out: list[bytes] = []
    node = CameraNode(cfg, out.append, key=KEY, sensor=sensor_from_config(cfg, scene)).start()
    try:
        for k in range(5):
            node.offer(k, k * PERIOD_NS, moving_pose(cfg, k * 0.02), True)
            deadline = time.monotonic() + 10
            while len(out) + node.stats.render_errors < k + 1 and time.monotonic() < deadline:
                time.sleep(0.005)
    finally:
        node.close()
    assert [decode_frame(b).period for b in out] == [0, 1, 3, 4]
    assert node.stats.render_errors == 1
    assert "camera: frame lost: ValueError: texture unavailable" in capsys.readouterr().err
