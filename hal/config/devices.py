"""The sections of the rig's other parts: ``[dsp]`` (the emulated DSP node), ``[transport]``
(the links between the processes) and ``[vision]`` (the vision pipeline's calibrated camera)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from hal.config.values import Vec2


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
    lockstep_reply_timeout_s: float = 0.5
    """Lockstep: real time the DSP waits for a period's command before it counts the period
    missing and steps with the held torque (the watchdog then counts it). Raise it on a host so
    loaded that the controller stalls this long: each missing period makes the run unclean."""
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
    """python-can ``INTERFACE[:CHANNEL]``; auto = the interface of python-can's configuration
    (``CAN_INTERFACE``, ``~/can.conf``), else socketcan:vcan0 if present, else udp_multicast."""
    zenoh_endpoint: str = "tcp/127.0.0.1:7447"
    """Loopback endpoint the processes meet on."""
    zenoh_config: str = ""
    """Path of a zenoh json5 config replacing the loopback defaults (multi-host setups)."""
    key_file: str = ""
    """Path of the rig key (``hil keygen FILE``, mode 0600): authenticates CAN frames and vision
    messages (hal/secoc.py). Required by every process of a rig; ``hil up`` makes a fresh one
    per run unless given ``--key-file``."""


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
    rt_priority: int = 60
    """Realtime: SCHED_FIFO priority of the thread that measures the frames (best effort; 0 =
    normal scheduling). Below the controller's (80) and the emulated DSP's and camera's (70,
    69): on a busy host a normal thread waits behind every other process for its turn, and a
    frame's features come late by as much."""
