"""The emulator's physics and the controller's nominal model are independent implementations:
drive both with the same torques and check that they agree."""

from __future__ import annotations

import numpy as np
import pytest

from hal.config import RigConfig
from plant_emulator.arm import ArmPhysics
from plant_emulator.camera import camera_pose, project
from plant_emulator.world import World
from tests.support import nominal_rk4
from tests.support.nominal_model import NumpyModel

RNG = np.random.default_rng(7)


@pytest.mark.parametrize("gravity", [0.0, 9.81])
def test_same_torque_sequence_same_motion(cfg: RigConfig, gravity: float):
    cfg = cfg.with_overrides({"robot.gravity": gravity})
    world, model = World(cfg), NumpyModel.from_config(cfg)
    q, dq = world.q.copy(), world.dq.copy()
    for _ in range(100):  # 2 s of random torques held for 20 ms each
        tau = RNG.uniform(-1, 1, 2) * np.array([5.0, 0.5])
        world.hold(tau, cfg.rates.substeps)
        for _ in range(cfg.rates.substeps):
            q, dq = nominal_rk4(model, q, dq, tau, world.dt)
    np.testing.assert_allclose(world.q, q, atol=1e-9)
    np.testing.assert_allclose(world.dq, dq, atol=1e-8)
    assert np.ptp(world.q) > 0  # it actually moved


def test_dynamics_terms_agree(cfg: RigConfig):
    cfg = cfg.with_overrides({"robot.gravity": 9.81})
    arm, model = ArmPhysics(cfg.robot), NumpyModel.from_config(cfg)
    for _ in range(100):
        q, dq = RNG.uniform(-np.pi, np.pi, 2), RNG.normal(0, 3, 2)
        np.testing.assert_allclose(arm.inertia(q), model.M(q), rtol=1e-12)
        np.testing.assert_allclose(arm.coriolis(q, dq), model.C(q, dq) @ dq, atol=1e-12)
        np.testing.assert_allclose(arm.gravity(q), model.g(q), atol=1e-12)


def test_camera_agrees_with_eq6(cfg: RigConfig):
    model = NumpyModel.from_config(cfg)
    for _ in range(100):
        q, target = RNG.uniform(-np.pi, np.pi, 2), RNG.uniform(-0.5, 0.5, 2)
        f = project(cfg.camera, camera_pose(cfg.robot, q), target)
        np.testing.assert_allclose(f, model.features(q, target), rtol=1e-12, atol=1e-10)


def test_paper_scenario_initial_features_and_jump(cfg: RigConfig):
    world = World(cfg)
    np.testing.assert_allclose(world.measure()[2], [-120.0, -160.0], atol=1e-9)
    world.hold(np.zeros(2), round(3.0 * cfg.rates.physics_hz))
    # Arm never moved, so the jumped target is seen exactly at f_jump.
    np.testing.assert_allclose(world.measure()[2], [-50.0, -64.0], atol=1e-9)


def test_torque_saturation_and_friction(cfg: RigConfig):
    cfg = cfg.with_overrides({"robot.viscous": [0.5, 0.05], "robot.coulomb": [0.2, 0.02]})
    world = World(cfg)
    world.hold(np.array([1000.0, -1000.0]), 1)
    np.testing.assert_allclose(world.tau_applied, [150.0, -15.0])
    world.hold(np.zeros(2), 2000)  # friction brings the free arm to rest
    assert np.all(np.abs(world.dq) < 0.05)


def test_camera_frame_rate_noise_and_latency(cfg: RigConfig):
    cfg = cfg.with_overrides(
        {"camera.frame_rate_hz": 60.0, "camera.latency_s": 0.05, "camera.noise_px": 1.0}
    )
    world = World(cfg, seed=3)
    world.hold(np.zeros(2), 49)
    assert world.features() is None  # the first frame is still on its way
    errors = []
    for _ in range(200):
        world.hold(np.zeros(2), 5)
        frame = world.features()
        assert frame is not None
        assert world.t - 0.05 - 1 / 60 - 1e-9 <= frame.t_capture <= world.t - 0.05 + 1e-9
        assert frame.frame == round(frame.t_capture * 60)
        errors.append(frame.f - world.true_features())  # the arm is at rest
    assert np.std(errors) == pytest.approx(1.0, rel=0.2)
