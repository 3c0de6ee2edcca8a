"""The emulated camera sensor: lens model against OpenCV, rendering geometry, blur, determinism."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from hal.config import RigConfig
from plant_emulator.camera import CameraPose, camera_pose, project
from plant_emulator.camera_lens import Intrinsics, LensDistortion, distort, undistort
from plant_emulator.camera_sensor import CameraSensor, Resolution, SensorNoise
from plant_emulator.camera_textures import GridTexture, marker_texture
from plant_emulator.errors import CameraSensorError
from plant_emulator.scenario import paper_target

LENS = LensDistortion(k1=-0.21, k2=0.12, p1=0.0015, p2=-0.0008, k3=-0.03)
K = Intrinsics(1230.0, 1236.0, 322.3, 236.9)


def sensor(noise=None, lens=None, exposure=0.0, scene=None, seed=1):
    cfg = RigConfig()
    target = paper_target(cfg)
    return CameraSensor(
        Intrinsics(1230.0, 1230.0, 319.5, 239.5),
        lens or LensDistortion(),
        Resolution(640, 480),
        noise or SensorNoise(),
        exposure,
        seed,
        z_wo=0.9,
        scene=scene or (lambda t: marker_texture(target.position(t))),
    )


def grid_points(n: int = 400) -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.uniform([-0.3, -0.22], [0.3, 0.22], (n, 2))


def test_forward_lens_matches_opencv_project_points():
    pts = grid_points()
    xd, yd = distort(pts[:, 0], pts[:, 1], LENS)
    obj = np.column_stack([pts, np.ones(len(pts))])
    uv, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), K.matrix(), LENS.coefficients())
    ours = np.column_stack([K.cx + K.fx * xd, K.cy + K.fy * yd])
    np.testing.assert_allclose(ours, uv[:, 0, :], atol=1e-9)


def test_undistort_round_trips_and_agrees_with_opencv():
    pts = grid_points()
    xd, yd = distort(pts[:, 0], pts[:, 1], LENS)
    xn, yn, ok = undistort(xd, yd, LENS)
    assert ok.all()
    np.testing.assert_allclose(np.column_stack([xn, yn]), pts, atol=1e-12)
    uv = np.column_stack([K.cx + K.fx * xd, K.cy + K.fy * yd]).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    cv = cv2.undistortPoints(uv, K.matrix(), LENS.coefficients(), None, None, None, crit)
    np.testing.assert_allclose(cv[:, 0, :], pts, atol=1e-9)


def test_sensor_refuses_a_lens_it_cannot_invert():
    with pytest.raises(CameraSensorError, match="cannot be inverted"):
        sensor(lens=LensDistortion(k1=-3.0))


def centroid(img: np.ndarray, paper_dn: float) -> np.ndarray:
    w = np.clip(paper_dn - img.astype(float), 0, None)
    vv, uu = np.indices(img.shape)
    return np.array([(w * uu).sum() / w.sum(), (w * vv).sum() / w.sum()])


@pytest.mark.parametrize("lens", [LensDistortion(), LENS], ids=["pinhole", "distorted"])
def test_marker_is_drawn_where_eq6_and_the_lens_put_it(lens):
    """Over a grid of poses, the disc's grey-weighted centroid is where the true lens maps the
    target: on a pinhole camera, exactly eq. (6) about the principal point."""
    cfg = RigConfig()
    target = paper_target(cfg).position(0.0)
    s = sensor(lens=lens)
    q0 = np.array(cfg.scenario.q0)
    errs = []
    for d1 in np.linspace(-0.04, 0.04, 3):
        for d2 in np.linspace(-0.06, 0.06, 3):
            pose = camera_pose(cfg.robot, q0 + np.array([d1, d2]))
            img = s.render(lambda t, p=pose: p, 0.0)
            expected = s.project(pose, target[0], target[1])
            if lens.none:
                f = project(cfg.camera, pose, target)
                np.testing.assert_allclose(expected - [319.5, 239.5], f, atol=1e-9)
            errs.append(centroid(img, 0.8 * 255) - expected)
    rms = float(np.sqrt(np.mean(np.square(errs))))
    # measured 0.003 px (pinhole) and 0.02 px (distorted: a distorted disc's centroid is not the
    # image of its centre); the bounds leave room for rounding to 8 bits only
    assert rms < (0.01 if lens.none else 0.05)


def test_noise_is_a_function_of_seed_and_frame_only():
    pose = CameraPose(0.5, 0.3, 0.2)
    a = sensor(noise=SensorNoise(20.0, 1.0), seed=7)
    b = sensor(noise=SensorNoise(20.0, 1.0), seed=7)
    f3 = a.render(lambda t: pose, 0.1, frame=3)
    b.render(lambda t: pose, 0.1, frame=0)
    np.testing.assert_array_equal(f3, b.render(lambda t: pose, 0.1, frame=3))
    assert not np.array_equal(f3, a.render(lambda t: pose, 0.1, frame=4))
    c = sensor(noise=SensorNoise(20.0, 1.0), seed=8)
    assert not np.array_equal(f3, c.render(lambda t: pose, 0.1, frame=3))
    clean = sensor().render(lambda t: pose, 0.1).astype(float)
    resid = f3.astype(float) - clean
    paper = clean == round(0.8 * 255)
    expected = np.sqrt(0.8 * 255 / 20.0 + 1.0)
    assert resid[paper].std() == pytest.approx(expected, rel=0.05)


def test_motion_blur_averages_the_exposure():
    """A camera moving at constant speed: the blurred disc's centroid is the disc at mid
    exposure, and it is smeared along the motion by speed x exposure."""
    cfg = RigConfig()
    target = paper_target(cfg).position(0.0)
    p0 = camera_pose(cfg.robot, np.array(cfg.scenario.q0))
    v = 0.5  # m/s along x_w: 683 px/s at 1367 px/m

    def pose_at(t: float) -> CameraPose:
        return CameraPose(p0.x + v * t, p0.y, p0.phi)

    exposure = 0.01
    s = sensor(exposure=exposure)
    times = s.subexposures(pose_at, 0.0)
    assert len(times) > 20
    blurred = s.render(pose_at, 0.0)
    still = sensor().render(pose_at, 0.0)
    mid = s.project(pose_at(0.0), target[0], target[1])
    np.testing.assert_allclose(centroid(blurred, 0.8 * 255), mid, atol=0.02)
    smear = v * exposure * cfg.camera.gain

    def ramp(img: np.ndarray) -> int:
        """Width of the not-paper region minus the width of the full-ink core (px)."""
        return int((img < 195).sum(axis=1).max() - (img < 45).sum(axis=1).max())

    # the edges' ramps widen by the smear on both sides
    assert ramp(blurred) - ramp(still) == pytest.approx(2 * smear, abs=2.5)
    assert len(sensor(exposure=exposure).subexposures(lambda t: p0, 0.0)) == 1


def test_grid_texture_box_filter_keeps_cell_averages():
    """A checkerboard seen at a footprint of a whole cell averages to the mean reflectance;
    at a tiny footprint it is the cell value."""
    cells = np.indices((4, 4)).sum(axis=0) % 2 * 0.6 + 0.2
    tex = GridTexture(cells, (0.0, 0.0), 0.01, 0.5)
    x = np.array([0.005, 0.015, 0.01, 0.03])
    y = np.array([0.005, 0.005, 0.01, 0.035])
    np.testing.assert_allclose(tex.sample(x, y, np.full(4, 1e-6))[:2], [0.2, 0.8])
    np.testing.assert_allclose(tex.sample(x, y, np.full(4, 0.01))[2:], [0.5, 0.5])
    assert tex.sample(np.array([-1.0]), np.array([-1.0]), np.array([0.001]))[0] == 0.5


def test_target_out_of_view_leaves_a_blank_frame():
    pose = CameraPose(5.0, 5.0, 0.0)
    img = sensor().render(lambda t: pose, 0.0)
    assert (img == round(0.8 * 255)).all()


def test_a_frame_rendered_on_its_prepared_background_has_the_whole_frames_pixels():
    """The camera makes the next frame's background and noise ahead (:meth:`prepare`) and then
    exposes only the target's region: the pixels are those of exposing the whole frame's
    reflectance, still and blurred, with a lens, in and out of view; a background prepared for
    another frame, seed or reflectance is not used."""
    cfg = RigConfig()
    p0 = camera_pose(cfg.robot, np.array(cfg.scenario.q0))
    rng = np.random.default_rng(3)
    s = sensor(noise=SensorNoise(40.0, 0.5), lens=LENS, exposure=0.004, seed=11)
    paper = 0.8
    for frame in range(12):
        dx, dy, dphi = rng.normal(0.0, 0.05, 3) if frame != 5 else (5.0, 5.0, 0.0)
        v = rng.normal(0.0, 0.5, 2) if frame % 2 else np.zeros(2)

        def pose_at(t, dx=dx, dy=dy, dphi=dphi, v=v):
            return CameraPose(p0.x + dx + v[0] * t, p0.y + dy + v[1] * t, p0.phi + dphi)

        whole = s.expose(s.irradiance(pose_at, 0.0), frame)
        prepared_for = [(frame, paper), (frame + 1, paper), (frame, 0.5)][frame % 3]
        s.prepare(*prepared_for)
        np.testing.assert_array_equal(s.render(pose_at, 0.0, frame=frame), whole)
        np.testing.assert_array_equal(s.render(pose_at, 0.0, frame=frame), whole)  # unprepared
    s.prepare(0, paper)
    s.seed = 12
    fresh = sensor(noise=SensorNoise(40.0, 0.5), lens=LENS, exposure=0.004, seed=12)
    np.testing.assert_array_equal(
        s.render(lambda t: p0, 0.0, frame=0), fresh.render(lambda t: p0, 0.0, frame=0)
    )


class _AnyTexture:
    """A texture the sensor knows only through the PlaneTexture protocol (its numpy path)."""

    def __init__(self, inner):
        self.inner = inner
        self.background = inner.background

    def support(self):
        return self.inner.support()

    def sample(self, x, y, footprint):
        return self.inner.sample(x, y, footprint)

    def __eq__(self, other):
        return isinstance(other, _AnyTexture) and other.inner == self.inner


@pytest.mark.parametrize("lens", [LensDistortion(), LENS], ids=["pinhole", "distorted"])
def test_the_compiled_disc_exposure_matches_the_texture_sampled_by_numpy(lens):
    cfg = RigConfig()
    q0 = np.array(cfg.scenario.q0)
    disc = sensor(lens=lens, exposure=0.004)
    generic = sensor(lens=lens, exposure=0.004, scene=lambda t: _AnyTexture(disc.scene(t)))
    for dq in [(0.0, 0.0), (1.2, 8.3), (-0.4, 2.0)]:
        pose_at = lambda t, dq=dq: camera_pose(cfg.robot, q0 + np.array(dq) * t)  # noqa: E731
        assert (len(disc.subexposures(pose_at, 0.0)) > 1) == (dq != (0.0, 0.0))  # blurred
        a, b = disc.irradiance(pose_at, 0.0), generic.irradiance(pose_at, 0.0)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
        assert (a < 0.5).any()  # the disc is in the frame


def test_a_region_of_interest_has_the_whole_frames_pixels_there():
    """Region-of-interest readout (:meth:`render_window`): over several poses, still and
    blurred, with noise and a lens, windows around the target, cutting it, at the frame's
    corners and without it give exactly the whole frame's pixels of that region."""
    cfg = RigConfig()
    p0 = camera_pose(cfg.robot, np.array(cfg.scenario.q0))
    rng = np.random.default_rng(7)
    s = sensor(noise=SensorNoise(40.0, 0.5), lens=LENS, exposure=0.004, seed=5)
    windows = [(0, 0, 640, 480), (0, 0, 1, 1), (639, 479, 640, 480), (500, 10, 640, 200)]
    for frame in range(8):
        dx, dy, dphi = rng.normal(0.0, 0.03, 3)
        v = rng.normal(0.0, 0.5, 2) if frame % 2 else np.zeros(2)

        def pose_at(t, dx=dx, dy=dy, dphi=dphi, v=v):
            return CameraPose(p0.x + dx + v[0] * t, p0.y + dy + v[1] * t, p0.phi + dphi)

        whole = s.render(pose_at, 0.0, frame=frame)
        ys, xs = np.nonzero(whole < 100)  # the target's dark disc
        u, v0 = int(xs.mean()), int(ys.mean())
        around = [(u - 60, v0 - 60, u + 61, v0 + 61), (u - 5, v0 - 70, u + 3, v0 + 2)]
        for x0, y0, x1, y1 in windows + [
            (max(a, 0), max(b, 0), min(c, 640), min(d, 480)) for a, b, c, d in around
        ]:
            np.testing.assert_array_equal(
                s.render_window(pose_at, 0.0, (x0, y0, x1, y1), frame=frame),
                whole[y0:y1, x0:x1],
            )
    with pytest.raises(CameraSensorError):
        s.render_window(lambda t: p0, 0.0, (600, 0, 641, 10))
