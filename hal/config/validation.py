"""Validation of a whole :class:`~hal.config.rig.RigConfig`: every range and the cross-field
constraints, each failure a one-line :class:`~hal.errors.HalConfigError` naming the key."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from hal.config.cia402 import CONTROLLER_NODE_ID
from hal.config.control import LAW_NAMES
from hal.config.hardware import PROFILES
from hal.config.plant import plant_robot
from hal.config.ranges import RANGES, check_ranges
from hal.config.values import Mat2, shown
from hal.errors import HalConfigError
from hal.zenoh_endpoint import parse_loopback_endpoint

if TYPE_CHECKING:
    from hal.config.rig import RigConfig


def _require(cond: bool, key: str, message: str) -> None:
    if not cond:
        raise HalConfigError(f"{key}: {message}")


def _check_spd(matrix: Mat2, key: str) -> None:
    import numpy as np

    m = np.array(matrix)
    _require(np.allclose(m, m.T), key, f"must be symmetric, got {matrix}")
    _require(
        bool(np.all(np.linalg.eigvalsh(m) > 0.0)), key, f"must be positive definite, got {matrix}"
    )


def _value(cfg: RigConfig, key: str) -> object:
    section, _, name = key.partition(".")
    return getattr(getattr(cfg, section), name)


def validate(cfg: RigConfig, *, files: bool = True) -> RigConfig:
    """Check every setting's range (:data:`~hal.config.ranges.RANGES`) and the cross-field
    constraints; returns ``cfg`` or raises :class:`HalConfigError` naming the key. ``files``:
    also the files the configuration names that are read here (the drives' EDS); False for a
    configuration read back from a log, which may be read on a host without them."""

    def need(cond: bool, key: str, message: str) -> None:  # the error repeats the value
        _require(cond, key, f"{message}, got {shown(_value(cfg, key))}")

    r = cfg.robot
    for key in ("l1", "l2", "m1", "m2", "I1", "I2"):
        need(getattr(r, key) > 0, f"robot.{key}", "must be positive")
    for key in ("lc1", "lc2", "gravity"):
        need(getattr(r, key) >= 0, f"robot.{key}", "must be non-negative")
    for key in ("tau_max",):
        need(all(v > 0 for v in getattr(r, key)), f"robot.{key}", "must be positive")
    for key in ("viscous", "coulomb"):
        need(all(v >= 0 for v in getattr(r, key)), f"robot.{key}", "must be non-negative")
    c = cfg.camera
    need(c.s_lambda > 0, "camera.s_lambda", "must be positive")
    need(c.z_wo > 0, "camera.z_wo", "must be positive")
    need(c.noise_px >= 0, "camera.noise_px", "must be non-negative")
    need(c.frame_rate_hz >= 0, "camera.frame_rate_hz", "must be non-negative (0 = off)")
    need(c.latency_s >= 0, "camera.latency_s", "must be non-negative")
    _require(
        c.model in ("image", "analytic"),
        "camera.model",
        f"must be image or analytic, not {c.model!r}",
    )
    for key in ("focal_px", "principal_point_px"):
        pair = getattr(c, key)
        _require(
            pair == (0.0, 0.0) or min(pair) > 0,
            f"camera.{key}",
            f"must be (0, 0) (derived) or positive on both axes, got {list(pair)}",
        )
    g = cfg.gains
    need(g.kp > 0, "gains.kp", "must be positive")
    _check_spd(g.alpha, "gains.alpha")
    _check_spd(g.K, "gains.K")
    s = cfg.scenario
    _require(s.name == "paper", "scenario.name", f"unknown scenario {s.name!r} (known: paper)")
    need(s.jump_time >= 0, "scenario.jump_time", "must be non-negative")
    rt = cfg.rates
    for key in ("control_hz", "physics_hz", "state_hz", "status_hz"):
        need(getattr(rt, key) > 0, f"rates.{key}", "must be positive")
    _require(
        rt.physics_hz >= rt.control_hz,
        "rates.physics_hz",
        f"must be at least rates.control_hz ({rt.control_hz} Hz)",
    )
    ratio = rt.physics_hz / rt.control_hz
    _require(
        abs(ratio - round(ratio)) < 1e-9,
        "rates.physics_hz",
        f"must be an integer multiple of rates.control_hz (got ratio {ratio:g}; e.g. "
        f"rates.physics_hz = {_physics_that_fits(rt.control_hz, rt.physics_hz)})",
    )
    _require(
        rt.state_hz <= rt.physics_hz,
        "rates.state_hz",
        f"cannot exceed rates.physics_hz ({rt.physics_hz} Hz)",
    )
    h = cfg.rhc
    need(h.horizon > 0, "rhc.horizon", "must be positive")
    need(h.steps >= 1, "rhc.steps", "must be at least 1")
    need(h.kmax >= 1, "rhc.kmax", "must be at least 1")
    need(h.zeta > 0, "rhc.zeta", "must be positive")
    need(h.horizon_growth >= 0, "rhc.horizon_growth", "must be non-negative (0 = off)")
    need(all(v > 0 for v in h.u_max), "rhc.u_max", "must be positive")
    need(h.dummy_weight > 0, "rhc.dummy_weight", "must be positive")
    need(0 < h.fd_step < 1e-2, "rhc.fd_step", "must be in (0, 0.01)")
    need(h.residual_bound > 0, "rhc.residual_bound", "must be positive")
    need(h.init_tol > 0, "rhc.init_tol", "must be positive")
    need(h.init_iterations >= 1, "rhc.init_iterations", "must be at least 1")
    ct = cfg.controller
    _require(
        ct.law in LAW_NAMES,
        "controller.law",
        f"must be {', '.join(LAW_NAMES[:-1])} or {LAW_NAMES[-1]}, not {ct.law!r}",
    )
    _require(
        ct.clock in ("realtime", "lockstep"),
        "controller.clock",
        f"must be realtime or lockstep, not {ct.clock!r}",
    )
    _require(
        cfg.hardware.profile in PROFILES,
        "hardware.profile",
        f"must be {' or '.join(PROFILES)}, not {cfg.hardware.profile!r}",
    )
    need(ct.feature_timeout_s > 0, "controller.feature_timeout_s", "must be positive")
    need(ct.state_timeout_s > 0, "controller.state_timeout_s", "must be positive")
    need(ct.spin_us >= 0, "controller.spin_us", "must be non-negative")
    period_us = 1e6 / rt.control_hz
    _require(  # a spin of a whole period leaves no time to wait or read ahead: a busy loop
        ct.spin_us < period_us,
        "controller.spin_us",
        f"must be less than the control period ({period_us:g} us at rates.control_hz "
        f"{rt.control_hz:g}), got {ct.spin_us:g}",
    )
    need(1 <= ct.rt_priority <= 99, "controller.rt_priority", "must be in 1..99")
    d = cfg.dsp
    need(d.watchdog_periods > 0, "dsp.watchdog_periods", "must be positive")
    need(d.encoder_counts >= 2, "dsp.encoder_counts", "must be at least 2")
    need(d.velocity_filter_hz >= 0, "dsp.velocity_filter_hz", "must be non-negative")
    _require(
        d.state_sync in ("command", "free"),
        "dsp.state_sync",
        f"must be command or free, got {d.state_sync!r}",
    )
    check_ranges(cfg)
    _check_principal_point(cfg)
    _check_plant(cfg)
    for j in range(2):
        _require(
            d.q_min[j] < d.q_max[j],
            "dsp.q_min",
            f"must be below dsp.q_max on every joint, got {d.q_min} and {d.q_max}",
        )
    for j, q in enumerate(s.q0):
        _require(
            d.q_min[j] <= q <= d.q_max[j],
            "scenario.q0",
            f"must lie within dsp.q_min {d.q_min} .. dsp.q_max {d.q_max}, got {s.q0}",
        )
    _check_cia402(cfg)
    if files:
        _check_drive_eds(cfg)
    _check_transport(cfg)
    return cfg


def _physics_that_fits(control_hz: float, physics_hz: float) -> str:
    """The multiple of ``control_hz`` next above ``physics_hz`` (below, where that is beyond
    the range of ``rates.physics_hz``), as a TOML value."""
    _, hi, _ = RANGES["rates.physics_hz"]
    multiple = control_hz * math.ceil(physics_hz / control_hz)
    if multiple > hi:
        multiple = control_hz * math.floor(physics_hz / control_hz)
    return f"{round(multiple, 6):.12g}"


def _check_principal_point(cfg: RigConfig) -> None:
    """The principal point inside the image; after the ranges, so that a bad image size is
    its own key's error, not this one's."""
    c = cfg.camera
    cx, cy = c.true_principal_point_px
    _require(
        cx < c.width_px and cy < c.height_px,
        "camera.principal_point_px",
        f"must lie inside the {c.width_px}x{c.height_px} image, got ({cx:g}, {cy:g})",
    )


def _check_cia402(cfg: RigConfig) -> None:
    c = cfg.cia402
    if cfg.hardware.profile == "cia402":
        _check_drive_period(cfg)
    _require(c.node_id_1 != c.node_id_2, "cia402.node_id_2", "must differ from node_id_1")
    for key, node in (("cia402.node_id_1", c.node_id_1), ("cia402.node_id_2", c.node_id_2)):
        _require(
            node != CONTROLLER_NODE_ID,
            key,
            f"{node} is the controller's own node id (its heartbeat); give the drive 1..126",
        )
    for j, rated in enumerate(c.rated_torque):
        _require(
            cfg.robot.tau_max[j] / rated * 1000 <= 32767,
            "cia402.rated_torque",
            f"{rated!r} Nm on joint {j + 1}: robot.tau_max {cfg.robot.tau_max[j]!r} Nm would be "
            f"{cfg.robot.tau_max[j] / rated * 1000:.0f} per mille, beyond INT16 (32767)",
        )


def _check_drive_eds(cfg: RigConfig) -> None:
    """Each configured drive EDS (``cia402.eds_1``, ``eds_2``) read and holding every object
    the master needs, whatever the profile (``hil cia402 check`` takes any configuration);
    the empty default, the shipped EDS, is not read again."""
    c = cfg.cia402
    if not (c.eds_1 or c.eds_2):
        return
    from hal.cia402_master.eds import check_eds, configured  # imports canopen: only when set

    for key, value, node_id in configured(cfg):
        if value:
            check_eds(key, value, node_id)


def _check_transport(cfg: RigConfig) -> None:
    """The zenoh endpoint with the configuration, not when the first session opens (a run's
    recorder would have started by then): loopback only, unless a zenoh config file replaces
    the loopback defaults (empty: the default endpoint)."""
    t = cfg.transport
    if t.zenoh_endpoint and not t.zenoh_config:
        parse_loopback_endpoint(t.zenoh_endpoint)


def _check_drive_period(cfg: RigConfig) -> None:
    """The cia402 profile writes the control period to every drive's 0x60C2 exactly (the
    emulated drives boot with the same value): a rate it cannot write is refused here, before
    any process starts, not at the drives' boot."""
    from hal.cia402_master.units import interpolation_period  # imports canopen: cia402 only

    hz = cfg.rates.control_hz
    try:
        interpolation_period(1.0 / hz)
    except HalConfigError as exc:
        raise HalConfigError(
            f"rates.control_hz: {hz:g} Hz with hardware.profile cia402: {exc}"
        ) from exc


def _check_plant(cfg: RigConfig) -> None:
    r, p = cfg.robot, cfg.plant
    if p.theta3 != 1.0 and r.lc2 == 0:
        raise HalConfigError("plant.theta3: robot.lc2 is 0, so theta3 = 0 cannot be scaled")
    plant = plant_robot(cfg)
    for key, inertia in (("theta1", plant.I1), ("theta2", plant.I2)):
        _require(
            inertia > 0,
            f"plant.{key}",
            f"{getattr(p, key)!r} (with plant.theta3 {p.theta3!r}) leaves the plant's link "
            f"inertia I{key[-1]} at {inertia:.4g} kg·m², not positive",
        )


def image_noise_error(cfg: RigConfig) -> str | None:
    """Why ``cfg`` cannot run on the rendering camera, or None: ``camera.noise_px`` is the
    analytic camera's Gaussian pixel noise (``camera.model = "analytic"``, ``hil simulate``);
    a rendered frame's features are as noisy as its sensor makes them, and a pixel noise
    that nothing applies must not be reported as the run's."""
    c = cfg.camera
    if c.model != "image" or c.noise_px == 0:
        return None
    return (
        f"camera.noise_px = {c.noise_px:g} is the analytic camera's pixel noise, and this "
        "camera renders images (camera.model = image): their noise is the sensor's "
        "(camera.read_noise_dn, camera.electrons_per_dn, seeded by camera.seed); set "
        "camera.noise_px = 0, or camera.model = analytic"
    )
