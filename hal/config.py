"""Rig configuration: one TOML format for robot, camera, gains, scenario, rates and transports.

Every section is a frozen dataclass whose defaults are the paper's numbers (Pelican arm, the
paper's gains of eq. 34, the "paper" scenario). :func:`load_config` validates a file once at
start-up and raises :class:`~hal.errors.HalConfigError` naming the offending key. The config lives
in :mod:`hal` because both sides of the rig (controller and emulator) read the same file.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hal.errors import HalConfigError

LAW_NAMES = ("pbc", "ioc", "rhc")
"""Control-law names (``controller.law``, ``--law``); rt_controller's law table has one entry
per name (``rt_controller.control.law_table.LAWS``, checked by a test)."""

if TYPE_CHECKING:  # numpy is imported where used: `hil --help` does not need it
    import numpy as np

Vec2 = tuple[float, float]
Mat2 = tuple[tuple[float, float], tuple[float, float]]


def _diag(a: float, b: float) -> Mat2:
    return ((a, 0.0), (0.0, b))


@dataclass(frozen=True)
class RobotConfig:
    """Two-link planar arm (eq. 1-5). Lengths in m, masses in kg, inertias in kg·m²."""

    l1: float = 0.26
    l2: float = 0.26
    lc1: float = 0.0983
    lc2: float = 0.0229
    m1: float = 6.5225
    m2: float = 2.0458
    I1: float = 0.1213
    I2: float = 0.0116
    gravity: float = 0.0
    """Gravity along -Y_w in m/s²; 0 for the horizontal plane of the paper's rig."""
    tau_max: Vec2 = (150.0, 15.0)
    """Amplifier torque limits per joint, N·m."""
    viscous: Vec2 = (0.0, 0.0)
    """Viscous joint friction, N·m·s/rad (emulator only)."""
    coulomb: Vec2 = (0.0, 0.0)
    """Coulomb joint friction, N·m (emulator only)."""

    @property
    def theta(self) -> tuple[float, float, float]:
        """Base parameters theta1..theta3 of eq. (4)-(5)."""
        t1 = self.m1 * self.lc1**2 + self.m2 * self.l1**2 + self.I1
        t2 = self.m2 * self.lc2**2 + self.I2
        t3 = self.m2 * self.l1 * self.lc2
        return (t1, t2, t3)


@dataclass(frozen=True)
class CameraConfig:
    """Ideal pinhole camera on the hand (eq. 6): f = (s·lambda / z_wo) R_wc^T (p_wo - p_wc)."""

    s_lambda: float = 1230.0
    """Scale factor times focal length, px."""
    z_wo: float = 0.9
    """Depth of the target plane, m."""
    noise_px: float = 0.0
    """Standard deviation of Gaussian pixel noise on each feature; 0 = off."""
    frame_rate_hz: float = 0.0
    """Camera frame rate; 0 = the default: 60 fps (the XC-HR57's) for ``hil vision`` and the
    emulated camera in realtime and the analytic vision process in lockstep, a fresh image
    whenever the controller asks in ``hil simulate``. The emulated camera in lockstep gives
    exactly one frame per control period whatever this is."""
    latency_s: float = 0.0
    """Delay between capture and delivery of a feature vector; 0 = off."""
    seed: int = 0
    """Seed of the pixel-noise generator (repetitions of an experiment differ by it)."""
    model: str = "image"
    """image: the emulated camera renders frames and the vision process measures f from the
    pixels (``hil up``, ``hil experiment``); analytic: f from eq. (6) plus ``noise_px`` (fast
    sweeps, ``hil simulate``)."""
    width_px: int = 640
    """Image width of the emulated camera, px."""
    height_px: int = 480
    """Image height of the emulated camera, px."""
    principal_point_px: Vec2 = (0.0, 0.0)
    """True principal point (cx, cy), px; (0, 0): the image centre ((w - 1) / 2, (h - 1) / 2)."""
    focal_px: Vec2 = (0.0, 0.0)
    """True focal lengths (fx, fy), px; (0, 0): s·lambda on both axes (square pixels, eq. 6)."""
    lens_k1: float = -0.1
    """True lens of the emulated camera, OpenCV's model: radial k1."""
    lens_k2: float = 0.05
    """True lens: radial k2."""
    lens_p1: float = 0.0
    """True lens: tangential p1."""
    lens_p2: float = 0.0
    """True lens: tangential p2."""
    lens_k3: float = 0.0
    """True lens: radial k3."""
    exposure_s: float = 0.004
    """Exposure time; the frame is stamped at its middle and blurred by the motion during it
    (0: an instant, no blur)."""
    electrons_per_dn: float = 40.0
    """Shot noise: photo-electrons per grey level (variance DN / this); 0 = off."""
    read_noise_dn: float = 0.5
    """Read noise, standard deviation in grey levels; 0 = off."""
    image_log_fps: float = 10.0
    """Rate of the decimated image stream in the log and on ``hil monitor``; 0 = none."""

    @property
    def gain(self) -> float:
        """s·lambda / z_wo in px/m (1367 for the paper's camera)."""
        return self.s_lambda / self.z_wo

    @property
    def true_focal_px(self) -> tuple[float, float]:
        """The emulated camera's (fx, fy), px (``focal_px``, or s·lambda)."""
        fx, fy = self.focal_px
        return (fx, fy) if (fx, fy) != (0.0, 0.0) else (self.s_lambda, self.s_lambda)

    @property
    def true_principal_point_px(self) -> tuple[float, float]:
        """The emulated camera's (cx, cy), px (``principal_point_px``, or the image centre)."""
        cx, cy = self.principal_point_px
        if (cx, cy) != (0.0, 0.0):
            return (cx, cy)
        return ((self.width_px - 1) / 2, (self.height_px - 1) / 2)

    @property
    def true_lens(self) -> tuple[float, float, float, float, float]:
        """The emulated camera's distortion coefficients in OpenCV's order."""
        return (self.lens_k1, self.lens_k2, self.lens_p1, self.lens_p2, self.lens_k3)


@dataclass(frozen=True)
class GainsConfig:
    """Controller gains of eq. (11), (13), (15), (18) and (34)."""

    kp: float = 0.13
    alpha: Mat2 = ((0.05, 0.0), (0.0, 0.15))
    K: Mat2 = ((0.01, 0.0), (0.0, 0.01))

    @property
    def R(self) -> np.ndarray:
        """R = kp/4 alpha^-1 + K (eq. 18)."""
        import numpy as np

        return self.kp / 4.0 * np.linalg.inv(np.array(self.alpha)) + np.array(self.K)


@dataclass(frozen=True)
class ScenarioConfig:
    """Initial pose, target placement and the target jump ("paper": the paper's Section V)."""

    name: str = "paper"
    q0: Vec2 = (math.pi / 6, -math.pi / 6)
    dq0: Vec2 = (0.0, 0.0)
    f0: Vec2 = (-120.0, -160.0)
    """Features at t = 0 (px); the target is placed so that the camera sees this."""
    disturbance: bool = True
    """Whether the target jumps at ``jump_time``."""
    jump_time: float = 3.0
    f_jump: Vec2 = (-50.0, -64.0)
    """Features the jumped target would have, seen from the camera's initial pose (px)."""


@dataclass(frozen=True)
class RatesConfig:
    """Loop rates in Hz."""

    control_hz: float = 50.0
    physics_hz: float = 1000.0
    state_hz: float = 1000.0
    """Rate of the camera poses the emulator publishes for vision, and of the DSP's joint-state
    frames with ``dsp.state_sync = free`` (``command``, the default, sends one state per control
    period, in step with the controller)."""
    status_hz: float = 10.0
    """Rate of the DSP's status frames."""

    @property
    def control_period_ns(self) -> int:
        return round(1e9 / self.control_hz)

    @property
    def substeps(self) -> int:
        """Physics steps per control period."""
        return round(self.physics_hz / self.control_hz)


@dataclass(frozen=True)
class RhcConfig:
    """Receding-horizon control (eq. 30) solved by C/GMRES."""

    horizon: float = 0.1
    """Final horizon length T_f, s."""
    steps: int = 10
    """Number of discretisation steps N of the horizon."""
    kmax: int = 5
    """GMRES iterations per update."""
    zeta: float = 50.0
    """Continuation stabilisation gain, 1/s (dF/dt = -zeta F)."""
    horizon_growth: float = 0.0
    """a in T(t) = T_f (1 - exp(-a t)); 0 keeps T = T_f from the start."""
    u_max: Vec2 = (150.0, 15.0)
    """Bounds |u_i| <= u_max,i enforced with dummy inputs, N·m."""
    dummy_weight: float = 0.01
    """Weight of the dummy inputs in the cost (keeps the bound multipliers finite)."""
    fd_step: float = 1e-8
    """Forward-difference step of the GMRES matrix-free products."""
    residual_bound: float = 1e3
    """Above this optimality residual the solution is rejected and the tick falls back."""
    init_tol: float = 1e-8
    """Residual target of the initial Newton-GMRES solve."""
    init_iterations: int = 50
    """Iteration limit of the initial Newton-GMRES solve."""


@dataclass(frozen=True)
class ControllerConfig:
    """Controller daemon settings."""

    law: str = "ioc"
    """pbc | ioc | rhc."""
    clock: str = "realtime"
    """realtime | lockstep."""
    feature_timeout_s: float = 0.1
    """Features older than this are stale."""
    outage_warn_periods: int = 5
    """A camera outage: more than this many ticks in a row on stale or invalid features. Each
    is a warning naming its start, its length and the longest (realtime and lockstep alike)."""
    outage_max_share: float = 0.25
    """A run that spent more than this share of its ticks (0-1) on stale or invalid features
    is not clean: its J is not the paper's experiment's."""
    state_timeout_s: float = 0.05
    """Joint states older than this mean the DSP went silent."""
    predict_state: bool = True
    """Realtime: bring the joint state up to the tick before the law sees it (the nominal model
    driven by the torques sent since the state arrived; the cycle record's ``predict_ms``). A
    tick that runs on the previous period's state (``late_states``) otherwise acts on a whole
    period of delay, which the paper's IOC and RHC gains do not tolerate. Lockstep states are
    sampled at the tick and are never predicted."""
    predict_features: bool = True
    """Realtime: bring the image features up to the tick before the law sees them: the target
    (static) seen from the predicted pose of now instead of the pose at capture (eq. 6; the
    cycle record's ``f_predict_ms``). Vision, zenoh and the camera make features one to three
    periods old on a busy host."""
    spin_us: float = 300.0
    """Busy-wait for the last microseconds before a deadline."""
    rehearse: bool = True
    """Realtime, at 200 Hz and below: shortly before each release (0.2 ms before the spin
    window) rehearse the last tick with nothing kept: its read (no drive state followed), its
    rule on a second controller, its write through a shadow codec to a private socket, so
    that the tick finds its code warm instead of paying for a period of sleep (the run's
    controller, its log, its counters and the bus are untouched)."""
    rt_priority: int = 80
    """SCHED_FIFO priority (best effort)."""
    cpu: int = -1
    """CPU to pin the loop to; -1 = leave affinity alone."""
    log_dir: str = "logs"
    max_clock_skew_s: float = 0.005
    """A feature message stamped further than this in the future (receive clock) is rejected
    (``future_stamp``): its age would come out negative and defeat the stale check."""
    feature_source_takeover_s: float = 1.0
    """After the first feature source id is locked in, another source id is rejected
    (``foreign_source``) unless the locked source sent nothing accepted for this long (a
    restarted vision process); 0 lets any new source take over at once."""
    rearm_after_trip: bool = True
    """Reset and re-enable the DSP once after each watchdog fault it reports (the trip means
    this loop was late); false leaves the amplifiers off. The run still counts as not clean."""
    rearm_after_restart: bool = False
    """Re-enable a DSP that restarted (new session) or was disabled by another node. Default:
    no: the controller holds zero torque, reports the mode and exits non-zero."""


@dataclass(frozen=True)
class DspConfig:
    """Emulated DSP node."""

    watchdog_periods: float = 3.0
    """Torque is removed after this many control periods without a valid command."""
    encoder_counts: int = 1_048_576
    """Encoder counts per revolution (20-bit absolute encoder)."""
    velocity_filter_hz: float = 200.0
    """Cut-off of the first-order velocity estimate filter; 0 = raw finite difference."""
    q_min: Vec2 = (-math.pi, -2.6)
    """Lowest joint angles, rad: with operation enabled, crossing one faults the DSP (torque off,
    ``DspStatus.FaultReason`` POSITION_LIMIT). Joint 1 may turn half a revolution either way;
    the elbow stops 2.6 rad (149 deg) short of folding link 2 onto link 1."""
    q_max: Vec2 = (math.pi, 2.6)
    """Highest joint angles, rad (see ``q_min``)."""
    dq_max: Vec2 = (10.0, 20.0)
    """Joint speed limits, rad/s: with operation enabled, exceeding one faults the DSP
    (VELOCITY_LIMIT). The paper scenario's live runs peak near 1.2 and 8.3 rad/s (the light
    elbow swings fast after the first torque); a runaway arm passes 20 rad/s within a second."""
    rt_priority: int = 70
    """Realtime: SCHED_FIFO priority of the DSP loop's thread (best effort; 0 = normal
    scheduling). The emulator stands in for hardware that is never starved: without it, a busy
    host delays its samples by whole periods. Below the controller's (80), so the controller
    still preempts it on a shared core."""
    state_sync: str = "command"
    """Realtime: when the joint state goes out (the camera pose for vision keeps ``state_hz``).
    ``command``: once
    per control period, ``state_lead_us`` before the controller's next tick, the phase learnt from
    the arrival of its torque commands (what a DSP synchronised to its master's cycle sends; on
    its own control-period clock until commands arrive); ``free``: at ``rates.state_hz`` on the
    DSP's own clock. Lockstep always sends the state with each Sync."""
    state_lead_us: float = 3000.0
    """``state_sync = command``: how long before the controller's tick the state is sampled; it
    covers the command's delay after the tick, one physics step and the transport."""


@dataclass(frozen=True)
class TransportConfig:
    """Where the processes talk."""

    can: str = "auto"
    """python-can ``INTERFACE[:CHANNEL]``; auto = socketcan:vcan0 if present else udp_multicast."""
    zenoh_endpoint: str = "tcp/127.0.0.1:7447"
    """Loopback endpoint the processes meet on."""
    zenoh_config: str = ""
    """Path of a zenoh json5 config replacing the loopback defaults (multi-host setups)."""
    key_file: str = ""
    """Path of the rig key (``hil keygen FILE``, mode 0600): authenticates CAN frames and vision
    messages (hal/secoc.py). Required by every process of a rig; ``hil up`` makes a fresh one
    per run unless given ``--key-file``."""


@dataclass(frozen=True)
class PlantConfig:
    """Model mismatch: how the emulated plant differs from the controller's nominal model.

    Factors on the nominal numbers of ``[robot]`` and ``[camera]`` (1 = the plant is the
    nominal model, the default). Only the emulator's physics, camera and vision apply them
    (:func:`plant_view`); the controller always works with the nominal sections, so a
    ``[plant]`` other than 1 is a plant the controller does not know exactly. Each run's config
    (its log's metadata, a sweep's row) carries the section.
    """

    theta1: float = 1.0
    """Factor on theta1 = m1 lc1² + m2 l1² + I1 (eq. 4), realised through the plant's I1."""
    theta2: float = 1.0
    """Factor on theta2 = m2 lc2² + I2, realised through the plant's I2."""
    theta3: float = 1.0
    """Factor on theta3 = m2 l1 lc2, realised through the plant's lc2 (I2 keeps theta2)."""
    s_lambda: float = 1.0
    """Factor on camera.s_lambda (scale factor times focal length)."""
    z_wo: float = 1.0
    """Factor on camera.z_wo (depth of the target plane)."""

    @property
    def nominal(self) -> bool:
        return all(getattr(self, f.name) == 1.0 for f in dataclasses.fields(self))


@dataclass(frozen=True)
class VisionConfig:
    """The vision pipeline's calibrated camera (``hil vision`` on frames; ``vision/``).

    Until ``vision.calibrated`` is true the detector uses the camera section's nominal values
    (the emulated camera's true lens); ``hil camera calibrate`` writes the keys below and sets it.
    """

    calibrated: bool = False
    """Whether the keys below hold a calibration (else the camera's nominal intrinsics)."""
    fx: float = 1230.0
    """Calibrated focal length along u, px."""
    fy: float = 1230.0
    """Calibrated focal length along v, px."""
    cx: float = 319.5
    """Calibrated principal point u, px."""
    cy: float = 239.5
    """Calibrated principal point v, px."""
    k1: float = 0.0
    """Radial distortion k1 (OpenCV's model)."""
    k2: float = 0.0
    """Radial distortion k2."""
    p1: float = 0.0
    """Tangential distortion p1."""
    p2: float = 0.0
    """Tangential distortion p2."""
    k3: float = 0.0
    """Radial distortion k3."""


@dataclass(frozen=True)
class RigConfig:
    """The whole rig: every section of the TOML file."""

    robot: RobotConfig = field(default_factory=RobotConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    gains: GainsConfig = field(default_factory=GainsConfig)
    scenario: ScenarioConfig = field(default_factory=ScenarioConfig)
    rates: RatesConfig = field(default_factory=RatesConfig)
    rhc: RhcConfig = field(default_factory=RhcConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    dsp: DspConfig = field(default_factory=DspConfig)
    transport: TransportConfig = field(default_factory=TransportConfig)
    plant: PlantConfig = field(default_factory=PlantConfig)
    vision: VisionConfig = field(default_factory=VisionConfig)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Plain nested dict (lists for tuples), the inverse of :func:`config_from_dict`."""
        return json.loads(json.dumps(dataclasses.asdict(self)))

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    def with_overrides(self, overrides: dict[str, Any]) -> RigConfig:
        """A validated copy with ``{"section.key": value}`` overrides applied (command-line
        options): every value gets the same type and range checks as in a file."""
        data = self.to_dict()
        for dotted, value in overrides.items():
            section, _, key = dotted.partition(".")
            if section not in data or not key:
                raise HalConfigError(f"unknown config key {dotted!r}")
            data[section][key] = list(value) if isinstance(value, tuple) else value
        return config_from_dict(data)


_SECTIONS: dict[str, type] = {f.name: f.type for f in dataclasses.fields(RigConfig)}
_SECTION_TYPES: dict[str, type] = {
    name: cls
    for name, cls in typing.get_type_hints(RigConfig).items()
    if dataclasses.is_dataclass(cls)
}


def _number(value: Any, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise HalConfigError(f"{key}: expected a number, got {value!r}")
    if not math.isfinite(value):
        raise HalConfigError(f"{key}: must be finite, got {value!r}")
    return float(value)


def _coerce(value: Any, hint: Any, key: str) -> Any:
    if hint is float:
        return _number(value, key)
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise HalConfigError(f"{key}: expected an integer, got {value!r}")
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise HalConfigError(f"{key}: expected true or false, got {value!r}")
        return value
    if hint is str:
        if not isinstance(value, str):
            raise HalConfigError(f"{key}: expected a string, got {value!r}")
        return value
    if hint == Vec2:
        if not isinstance(value, list | tuple) or len(value) != 2:
            raise HalConfigError(f"{key}: expected a list of 2 numbers, got {value!r}")
        return tuple(_number(v, f"{key}[{i}]") for i, v in enumerate(value))
    if hint == Mat2:
        if isinstance(value, list | tuple) and len(value) == 2:
            if all(isinstance(v, int | float) and not isinstance(v, bool) for v in value):
                return _diag(_number(value[0], f"{key}[0]"), _number(value[1], f"{key}[1]"))
            if all(isinstance(r, list | tuple) and len(r) == 2 for r in value):
                return tuple(
                    tuple(_number(v, f"{key}[{i}][{j}]") for j, v in enumerate(row))
                    for i, row in enumerate(value)
                )
        raise HalConfigError(
            f"{key}: expected a 2x2 matrix [[a, b], [c, d]] or its diagonal [a, d], got {value!r}"
        )
    raise HalConfigError(f"{key}: unsupported type {hint!r}")  # pragma: no cover


RETIRED_KEYS = {
    "controller.state_wait_us": "a tick never waits for its joint state (a late one is counted "
    "in late_states and its age compensated)",
    "controller.gil_switch_us": "the control process runs no other Python thread",
    "controller.recorder": "the MCAP log is always written by the recorder's own process",
}
"""Keys older versions had, with why they went: refused in a config file (with the reason),
ignored in a log's embedded config (they never changed what the per-tick rule computes)."""


def _build_section(name: str, data: Any, *, retired_ok: bool = False) -> Any:
    cls = _SECTION_TYPES[name]
    if not isinstance(data, dict):
        raise HalConfigError(f"[{name}]: expected a table, got {data!r}")
    hints = typing.get_type_hints(cls)
    known = [f.name for f in dataclasses.fields(cls)]
    kwargs = {}
    for key, value in data.items():
        why = RETIRED_KEYS.get(f"{name}.{key}")
        if why is not None:
            if retired_ok:
                continue
            raise HalConfigError(f"{name}.{key} was removed: {why}; delete it from the file")
        if key not in hints:
            raise HalConfigError(f"unknown key {name}.{key} (known keys: {', '.join(known)})")
        kwargs[key] = _coerce(value, hints[key], f"{name}.{key}")
    return cls(**kwargs)


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


_INT_MAX = 2**63 - 1
_RANGES: dict[str, tuple[float, float, str]] = {
    # key: (low, high, kind) -- kind "[]" closed, "(]" low open, "[)" high open, "()" open.
    "robot.l1": (0, 10, "(]"),
    "robot.l2": (0, 10, "(]"),
    "robot.lc1": (0, 10, "[]"),
    "robot.lc2": (0, 10, "[]"),
    "robot.m1": (0, 1e4, "(]"),
    "robot.m2": (0, 1e4, "(]"),
    "robot.I1": (0, 1e4, "(]"),
    "robot.I2": (0, 1e4, "(]"),
    "robot.gravity": (0, 100, "[]"),
    "robot.tau_max": (0, 1e4, "(]"),
    "robot.viscous": (0, 1e4, "[]"),
    "robot.coulomb": (0, 1e4, "[]"),
    "camera.s_lambda": (0, 1e6, "(]"),
    "camera.z_wo": (0, 1e3, "(]"),
    "camera.noise_px": (0, 1e4, "[]"),
    "camera.frame_rate_hz": (0, 1e4, "[]"),
    "camera.latency_s": (0, 10, "[]"),
    "camera.seed": (0, _INT_MAX, "[]"),
    "camera.width_px": (16, 8192, "[]"),
    "camera.height_px": (16, 8192, "[]"),
    "camera.principal_point_px": (0, 8192, "[]"),
    "camera.focal_px": (0, 1e6, "[]"),
    "camera.lens_k1": (-10, 10, "[]"),
    "camera.lens_k2": (-100, 100, "[]"),
    "camera.lens_p1": (-1, 1, "[]"),
    "camera.lens_p2": (-1, 1, "[]"),
    "camera.lens_k3": (-1000, 1000, "[]"),
    "camera.exposure_s": (0, 1, "[]"),
    "camera.electrons_per_dn": (0, 1e6, "[]"),
    "camera.read_noise_dn": (0, 255, "[]"),
    "camera.image_log_fps": (0, 1000, "[]"),
    "gains.kp": (0, 1e6, "(]"),
    "gains.alpha": (-1e6, 1e6, "[]"),
    "gains.K": (-1e6, 1e6, "[]"),
    "scenario.q0": (-50, 50, "[]"),
    "scenario.dq0": (-80, 80, "[]"),
    "scenario.f0": (-1e6, 1e6, "[]"),
    "scenario.jump_time": (0, 1e6, "[]"),
    "scenario.f_jump": (-1e6, 1e6, "[]"),
    "rates.control_hz": (1, 2000, "[]"),
    "rates.physics_hz": (1, 100_000, "[]"),
    "rates.state_hz": (1, 100_000, "[]"),
    "rates.status_hz": (1, 1000, "[]"),
    "rhc.horizon": (0, 10, "(]"),
    "rhc.steps": (1, 200, "[]"),
    "rhc.kmax": (1, 50, "[]"),
    "rhc.zeta": (0, 1e4, "(]"),
    "rhc.horizon_growth": (0, 1e4, "[]"),
    "rhc.u_max": (0, 1e4, "(]"),
    "rhc.dummy_weight": (0, 1e6, "(]"),
    "rhc.fd_step": (0, 1e-2, "()"),
    "rhc.residual_bound": (0, 1e12, "(]"),
    "rhc.init_tol": (0, 1, "(]"),
    "rhc.init_iterations": (1, 10_000, "[]"),
    "controller.feature_timeout_s": (0, 10, "(]"),
    "controller.outage_warn_periods": (0, 1e6, "[]"),
    "controller.outage_max_share": (0, 1, "[]"),
    "controller.state_timeout_s": (0, 10, "(]"),
    "controller.spin_us": (0, 100_000, "[]"),
    "controller.rt_priority": (1, 99, "[]"),
    "controller.cpu": (-1, 4095, "[]"),
    "controller.max_clock_skew_s": (0, 1, "[]"),
    "controller.feature_source_takeover_s": (0, 3600, "[]"),
    "dsp.watchdog_periods": (1, 100, "[]"),
    "dsp.encoder_counts": (2, 1 << 24, "[]"),
    "dsp.velocity_filter_hz": (0, 100_000, "[]"),
    "dsp.state_lead_us": (0, 1e6, "[]"),
    "dsp.rt_priority": (0, 99, "[]"),
    "dsp.q_min": (-50, 50, "[]"),
    "dsp.q_max": (-50, 50, "[]"),
    "dsp.dq_max": (0, 83, "(]"),
    "plant.theta1": (0.1, 10, "[]"),
    "plant.theta2": (0.1, 10, "[]"),
    "plant.theta3": (0, 10, "[]"),
    "plant.s_lambda": (0.1, 10, "[]"),
    "plant.z_wo": (0.1, 10, "[]"),
    "vision.fx": (0, 1e6, "(]"),
    "vision.fy": (0, 1e6, "(]"),
    "vision.cx": (-1e5, 1e5, "[]"),
    "vision.cy": (-1e5, 1e5, "[]"),
    "vision.k1": (-100, 100, "[]"),
    "vision.k2": (-100, 100, "[]"),
    "vision.p1": (-1, 1, "[]"),
    "vision.p2": (-1, 1, "[]"),
    "vision.k3": (-1000, 1000, "[]"),
}
"""Sane range of every numeric setting (each element of a vector or matrix): a value outside,
like ``rhc.steps = 1000000000`` or ``rates.physics_hz = 1e300``, is a one-line
:class:`HalConfigError` naming the key, before anything allocates or waits."""


def _in_range(value: float, lo: float, hi: float, kind: str) -> bool:
    above = value > lo if kind[0] == "(" else value >= lo
    below = value < hi if kind[1] == ")" else value <= hi
    return above and below


def _flat(value: Any) -> list[float]:
    if isinstance(value, list | tuple):
        return [v for item in value for v in _flat(item)]
    return [value]


def _check_ranges(cfg: RigConfig) -> None:
    for key, (lo, hi, kind) in _RANGES.items():
        section, _, name = key.partition(".")
        value = getattr(getattr(cfg, section), name)
        for v in _flat(value):
            if not (isinstance(v, int | float) and math.isfinite(v)):
                raise HalConfigError(f"{key}: must be finite, got {value!r}")
            if not _in_range(v, lo, hi, kind):
                interval = f"{kind[0]}{lo:g}, {hi:g}{kind[1]}"
                raise HalConfigError(f"{key}: {value!r} is out of range {interval}")


def validate(cfg: RigConfig) -> RigConfig:
    """Check every setting's range (:data:`_RANGES`) and the cross-field constraints; returns
    ``cfg`` or raises :class:`HalConfigError` naming the key."""
    r = cfg.robot
    for key in ("l1", "l2", "m1", "m2", "I1", "I2"):
        _require(getattr(r, key) > 0, f"robot.{key}", "must be positive")
    for key in ("lc1", "lc2", "gravity"):
        _require(getattr(r, key) >= 0, f"robot.{key}", "must be non-negative")
    for key in ("tau_max",):
        _require(all(v > 0 for v in getattr(r, key)), f"robot.{key}", "must be positive")
    for key in ("viscous", "coulomb"):
        _require(all(v >= 0 for v in getattr(r, key)), f"robot.{key}", "must be non-negative")
    c = cfg.camera
    _require(c.s_lambda > 0, "camera.s_lambda", "must be positive")
    _require(c.z_wo > 0, "camera.z_wo", "must be positive")
    _require(c.noise_px >= 0, "camera.noise_px", "must be non-negative")
    _require(c.frame_rate_hz >= 0, "camera.frame_rate_hz", "must be non-negative (0 = off)")
    _require(c.latency_s >= 0, "camera.latency_s", "must be non-negative")
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
    cx, cy = c.true_principal_point_px
    _require(
        cx < c.width_px and cy < c.height_px,
        "camera.principal_point_px",
        f"must lie inside the {c.width_px}x{c.height_px} image, got ({cx:g}, {cy:g})",
    )
    g = cfg.gains
    _require(g.kp > 0, "gains.kp", "must be positive")
    _check_spd(g.alpha, "gains.alpha")
    _check_spd(g.K, "gains.K")
    s = cfg.scenario
    _require(s.name == "paper", "scenario.name", f"unknown scenario {s.name!r} (known: paper)")
    _require(s.jump_time >= 0, "scenario.jump_time", "must be non-negative")
    rt = cfg.rates
    for key in ("control_hz", "physics_hz", "state_hz", "status_hz"):
        _require(getattr(rt, key) > 0, f"rates.{key}", "must be positive")
    _require(
        rt.physics_hz >= rt.control_hz,
        "rates.physics_hz",
        f"must be at least rates.control_hz ({rt.control_hz} Hz)",
    )
    ratio = rt.physics_hz / rt.control_hz
    _require(
        abs(ratio - round(ratio)) < 1e-9,
        "rates.physics_hz",
        f"must be an integer multiple of rates.control_hz (got ratio {ratio:g})",
    )
    _require(
        rt.state_hz <= rt.physics_hz,
        "rates.state_hz",
        f"cannot exceed rates.physics_hz ({rt.physics_hz} Hz)",
    )
    h = cfg.rhc
    _require(h.horizon > 0, "rhc.horizon", "must be positive")
    _require(h.steps >= 1, "rhc.steps", "must be at least 1")
    _require(h.kmax >= 1, "rhc.kmax", "must be at least 1")
    _require(h.zeta > 0, "rhc.zeta", "must be positive")
    _require(h.horizon_growth >= 0, "rhc.horizon_growth", "must be non-negative (0 = off)")
    _require(all(v > 0 for v in h.u_max), "rhc.u_max", "must be positive")
    _require(h.dummy_weight > 0, "rhc.dummy_weight", "must be positive")
    _require(0 < h.fd_step < 1e-2, "rhc.fd_step", "must be in (0, 0.01)")
    _require(h.residual_bound > 0, "rhc.residual_bound", "must be positive")
    _require(h.init_tol > 0, "rhc.init_tol", "must be positive")
    _require(h.init_iterations >= 1, "rhc.init_iterations", "must be at least 1")
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
    _require(ct.feature_timeout_s > 0, "controller.feature_timeout_s", "must be positive")
    _require(ct.state_timeout_s > 0, "controller.state_timeout_s", "must be positive")
    _require(ct.spin_us >= 0, "controller.spin_us", "must be non-negative")
    _require(1 <= ct.rt_priority <= 99, "controller.rt_priority", "must be in 1..99")
    d = cfg.dsp
    _require(d.watchdog_periods > 0, "dsp.watchdog_periods", "must be positive")
    _require(d.encoder_counts >= 2, "dsp.encoder_counts", "must be at least 2")
    _require(d.velocity_filter_hz >= 0, "dsp.velocity_filter_hz", "must be non-negative")
    _require(
        d.state_sync in ("command", "free"),
        "dsp.state_sync",
        f"must be command or free, got {d.state_sync!r}",
    )
    _check_ranges(cfg)
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
    return cfg


def _plant_robot(cfg: RigConfig) -> RobotConfig:
    """The plant's robot: the nominal one with theta1..theta3 scaled by ``[plant]``."""
    r, p = cfg.robot, cfg.plant
    if p.theta1 == p.theta2 == p.theta3 == 1.0:
        return r
    t1, t2, _ = r.theta
    lc2 = r.lc2 * p.theta3
    I2 = p.theta2 * t2 - r.m2 * lc2**2
    I1 = p.theta1 * t1 - r.m1 * r.lc1**2 - r.m2 * r.l1**2
    return dataclasses.replace(r, lc2=lc2, I1=I1, I2=I2)


def _check_plant(cfg: RigConfig) -> None:
    r, p = cfg.robot, cfg.plant
    if p.theta3 != 1.0 and r.lc2 == 0:
        raise HalConfigError("plant.theta3: robot.lc2 is 0, so theta3 = 0 cannot be scaled")
    plant = _plant_robot(cfg)
    for key, inertia in (("theta1", plant.I1), ("theta2", plant.I2)):
        _require(
            inertia > 0,
            f"plant.{key}",
            f"{getattr(p, key)!r} (with plant.theta3 {p.theta3!r}) leaves the plant's link "
            f"inertia I{key[-1]} at {inertia:.4g} kg·m², not positive",
        )


def plant_view(cfg: RigConfig) -> RigConfig:
    """What the emulated plant is: ``cfg`` with ``[robot]`` and ``[camera]`` replaced by the
    plant's numbers (the nominal ones times the ``[plant]`` factors) and ``[plant]`` back to 1.
    The emulator's physics, camera and vision are built from this; the controller never is."""
    p = cfg.plant
    if p.nominal:
        return cfg
    camera = dataclasses.replace(
        cfg.camera, s_lambda=cfg.camera.s_lambda * p.s_lambda, z_wo=cfg.camera.z_wo * p.z_wo
    )
    return dataclasses.replace(cfg, robot=_plant_robot(cfg), camera=camera, plant=PlantConfig())


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def config_from_dict(
    data: dict[str, Any], *, source: str | None = None, retired_ok: bool = False
) -> RigConfig:
    """Build and validate a :class:`RigConfig` from a nested dict (parsed TOML or JSON).

    Exactly the checks of a file (types, ranges, cross-field constraints); ``source`` (e.g.
    ``"log metadata"``) prefixes the one-line error, as the path does for a file;
    ``retired_ok`` skips :data:`RETIRED_KEYS` (a log written by an older version).
    """
    try:
        if not isinstance(data, dict):
            raise HalConfigError(f"config: expected a table of sections, got {type(data).__name__}")
        sections = {}
        for name, body in data.items():
            if name not in _SECTIONS:
                raise HalConfigError(
                    f"unknown section [{name}] (known sections: {', '.join(_SECTIONS)})"
                )
            sections[name] = _build_section(name, body, retired_ok=retired_ok)
        return validate(RigConfig(**sections))
    except HalConfigError as exc:
        msg = _one_line(str(exc))
        raise HalConfigError(f"{source}: {msg}" if source else msg) from None


def load_config(path: str | Path | None = None) -> RigConfig:
    """Load and validate a TOML rig config; ``None`` gives the embedded defaults."""
    if path is None:
        return validate(RigConfig())
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise HalConfigError(f"cannot read config file {p}: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise HalConfigError(
            f"{p}: not UTF-8 text (invalid byte 0x{raw[exc.start]:02x} at offset {exc.start})"
        ) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise HalConfigError(f"{p}: not valid TOML: {_one_line(str(exc))}") from None
    except RecursionError:
        raise HalConfigError(f"{p}: not valid TOML: nested too deeply") from None
    return config_from_dict(data, source=str(p))


def config_from_json(text: str | bytes, *, source: str = "embedded config") -> RigConfig:
    """Inverse of :meth:`RigConfig.to_json` (used to replay a log's embedded configuration);
    validated exactly like a file, errors prefixed with ``source``; keys older versions wrote
    and this one retired (:data:`RETIRED_KEYS`) are skipped."""
    try:
        data = json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise HalConfigError(f"{source}: not valid JSON: {_one_line(str(exc))}") from None
    return config_from_dict(data, source=source, retired_ok=True)
