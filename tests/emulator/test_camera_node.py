"""The emulated network camera: one frame per lockstep period, its own frame clock in realtime,
bit-exact for a seed, restarts with a scenario reset; region-of-interest readout for the frame
grabber."""

from __future__ import annotations

import numpy as np

from hal.camera_frame import RoiRequest, decode_frame
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


def test_a_pose_stamped_when_the_arm_was_there_gives_a_frame_stamped_from_it():
    """A SYNC-stepped world (the cia402 emulator) offers each pose with its SYNC's time: the
    frame's capture stamp is mid-exposure before it, not the moment the pose was offered."""
    cfg = RigConfig()
    out: list[bytes] = []
    clock = FakeClock()
    node = CameraNode(cfg, out.append, key=KEY, clock=clock)
    sync_ns = clock.now - 3_000_000  # the step and the TPDOs took 3 ms
    node.offer(0, 0, moving_pose(cfg, 0.0), True, sync_ns)
    node.offer(1, PERIOD_NS, moving_pose(cfg, 0.02), True)  # no stamp: offered now
    node.drain()
    stamps = [decode_frame(b).stamp_ns for b in out]
    assert stamps == [sync_ns - node.exposure_ns // 2, clock.now - node.exposure_ns // 2]


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
    from plant_emulator.camera_link import FramePublisher
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
    assert grabber.as_dict()["rejected"] == 0
    assert stranger.as_dict()["bad_mac"] == 20
    assert node.stats.publish_errors == 0


def test_a_frame_that_cannot_be_made_is_counted_and_the_camera_goes_on(capsys):
    """A scene that fails for one frame: that frame is lost (counted, one line on stderr), the
    worker keeps answering the next periods."""
    import time

    from plant_emulator.camera_rig import target_scene

    cfg = RigConfig()
    good = target_scene(cfg)
    bad_time = 2 * PERIOD_NS * 1e-9

    def scene(t: float):
        if abs(t - bad_time) < 0.003:
            raise ValueError("texture unavailable")
        return good(t)

    from plant_emulator.camera_rig import sensor_from_config

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


def roi_lockstep_run(periods: int = 16, ask=True, corner_at: int | None = None):
    """Lockstep camera and a real frame grabber (pipeline, image log) in process, the grabber's
    region requests fed back to the camera (``ask``); ``corner_at``: that frame's request is
    replaced by a region in a corner, without the target. Returns the node, the payloads sent,
    the features published, the image log's frames and the grabber."""
    from hal.camera_frame import FrameDecoder, encode_roi_request
    from hal.vision_image import VisionImage
    from vision.grabber import Grabber
    from vision.image_log import ImageLog
    from vision.intrinsics import intrinsics_from_config
    from vision.pipeline import Pipeline

    cfg = RigConfig()
    out: list[bytes] = []
    node = CameraNode(cfg, out.append, key=KEY, clock=FakeClock())
    decoder = FrameDecoder(key=KEY)
    logged: list[VisionImage] = []
    log = ImageLog(cfg.camera.image_log_fps, lambda image, lockstep: logged.append(image), 1)
    features = []
    grabber = Grabber(
        Pipeline(intrinsics_from_config(cfg)),
        features.append,
        source_id=1,
        image_log=log,
        request_roi=(lambda req: node.request(encode_roi_request(req, KEY))) if ask else None,
    )
    sent: list[bytes] = []
    for k in range(periods):
        if k == corner_at:
            node.request(encode_roi_request(RoiRequest(node.source, k, (0, 0, 40, 40)), KEY))
        sim = k * PERIOD_NS
        node.offer(k, sim, moving_pose(cfg, sim * 1e-9), True)
        node.drain()
        while out:
            payload = out.pop(0)
            sent.append(payload)
            frame = decoder.feed(payload)
            assert frame is not None
            grabber.on_frame(frame)
            node.drain()  # a frame asked again whole
    log.close()
    return node, sent, features, logged, grabber


def test_lockstep_regions_are_the_whole_frames_pixels_and_give_the_same_features():
    """With noise, motion blur and the lens on (the defaults): frames sent as regions of interest
    hold the whole frames' pixels there, the features are those of whole frames bit for bit, the
    first frame of each image-log slot is whole and the log gets only whole frames, and two
    runs send the same bytes."""
    node, sent, features, logged, grabber = roi_lockstep_run()
    _, whole_sent, whole_features, whole_logged, _ = roi_lockstep_run(ask=False)
    assert features == whole_features and len(features) == 16
    frames = [decode_frame(b) for b in sent]
    regions = [f for f in frames if f.is_roi]
    # whole: 0 (nothing asked yet, image-log slot -1: exposed around -2 ms), then the first
    # frame of each 100 ms slot, 1 (18 ms), 6 (118 ms), 11 (218 ms)
    assert node.stats.roi_frames == len(regions) == 12
    assert [f.seq for f in frames if not f.is_roi] == [0, 1, 6, 11]
    for f in regions:
        whole = decode_frame(whole_sent[f.seq]).pixels
        np.testing.assert_array_equal(
            f.pixels, whole[f.y0 : f.y0 + f.height, f.x0 : f.x0 + f.width]
        )
        assert f.width * f.height < 640 * 480 / 8
    assert len(logged) == len(whole_logged) == 4
    assert [m.frame for m in features if m.image] == [x.frame for x in logged]  # announced
    assert [x.png for x in logged] == [x.png for x in whole_logged]
    assert grabber.snapshot().roi_frames == 12
    _, again, *_ = roi_lockstep_run()

    def content(payloads):  # all but the random source id (and so the MAC)
        return [
            (f.seq, f.period, f.sim_time_ns, f.x0, f.y0, f.pixels.tobytes())
            for f in map(decode_frame, payloads)
        ]

    assert content(again) == content(sent)


def test_a_region_without_the_target_is_sent_again_whole():
    node, sent, features, _, grabber = roi_lockstep_run(periods=8, corner_at=3)
    _, _, whole_features, _, _ = roi_lockstep_run(periods=8, ask=False)
    assert features == whole_features
    assert (node.stats.whole_again, grabber.snapshot().roi_misses) == (1, 1)
    three = [decode_frame(b) for b in sent if decode_frame(b).seq == 3]
    assert [(f.is_roi, f.x0, f.width) for f in three] == [(True, 0, 40), (False, 0, 640)]


def test_bad_region_requests_are_counted_and_never_crash():
    from hal.camera_frame import encode_roi_request

    cfg = RigConfig().with_overrides({"camera.image_log_fps": 0})  # no slot sent whole
    out: list[bytes] = []
    node = CameraNode(cfg, out.append, key=KEY, clock=FakeClock())
    good = encode_roi_request(RoiRequest(node.source, 0, (600, 450, 700, 520)), KEY)
    for bad in (
        b"",
        b"junk" * 10,
        good[:-1],
        encode_roi_request(RoiRequest(1, 0, None), b"x" * 32),
    ):
        node.request(bad)
    node.request(encode_roi_request(RoiRequest(node.source ^ 1, 0, (0, 0, 50, 50)), KEY))
    node.request(good)  # reaches outside the frame: clamped
    node.offer(0, 0, moving_pose(cfg, 0.0), True)
    node.drain()
    f = decode_frame(out[0])
    assert (f.x0, f.y0, f.width, f.height) == (600, 450, 40, 30)
    s = node.stats
    assert (s.roi_rejected, s.roi_other, s.roi_requests, s.roi_clamped) == (4, 1, 1, 1)
    node.request(encode_roi_request(RoiRequest(node.source, 0, (0, 0, 5, 5)), KEY))  # too late
    node.request(encode_roi_request(RoiRequest(node.source, 7, None), KEY))  # not made yet
    node.drain()
    assert node.stats.roi_other == 2 and len(out) == 1
