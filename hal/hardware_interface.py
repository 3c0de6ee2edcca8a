"""The hardware seam of the controller, with a lifecycle (ros2_control's ``SystemInterface``).

A hardware profile is one class that speaks to one kind of rig: the DSP profile
(:class:`rt_controller.runtime.hardware.DspHardware`: the emulated or real DSP of ``hil.dbc``
over CAN, the features over zenoh) and the CiA 402 profile
(:class:`rt_controller.runtime.cia402_hardware.Cia402Hardware`). The controller's runtime
drives a profile only through :class:`HardwareInterface`, in this order::

    configure(stop)                    open the links, wait until the peer answers
    activate(now) ... until True       arm: walk the drive to *operation enabled*
    loop:  [step(timeout)]             lockstep only: the world's next period k
           read(now, judge) -> Observation
           write(tau, sync=k | None, release_ns=...)
    deactivate()                       zero torque, disable, links closed for this run

Who paces (``controller.clock``):

* **realtime**: the controller's monotonic clock. The runtime's pacer calls ``activate`` and
  then ``read``/``write`` once per period; between releases it may call ``wait_inputs`` so
  that ``read`` finds the inputs decoded.
* **lockstep**: the world is stepped one control period at a time, and ``step`` says when the
  next one is there. In the DSP profile the DSP's ``Sync(k)`` paces (the DSP advances its
  physics only after the command answering Sync k); in the CiA 402 profile the controller's
  own SYNC steps the world (``step`` sends SYNC k, then waits for the drive's PDOs and the
  features of period k). Either way ``write(tau, sync=k, ...)`` answers period k.

This module is pure declarations: :mod:`hal` may not import the runtime, and both profiles
import this module.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from hal.vision_codec import FeatureMsg


@dataclass(frozen=True)
class Observation:
    """What the read phase of one tick found (NaN where absent)."""

    q: np.ndarray
    dq: np.ndarray
    f: np.ndarray
    state_ns: int | None
    """Receive time of the joint state (None when stale)."""
    state_age_ms: float
    state_stale: bool
    f_age_ms: float
    f_stale: bool
    f_valid: bool
    drive_mode: str
    """The drive mode (:data:`hal.drive_state.MODES`); the law runs only in ``enabled``."""
    state_new: bool = True
    """A joint state arrived since the previous read (realtime: False means this period's
    state came late)."""
    actuation_delay_ms: float = 0.0
    """How long after the state's sampling the torque written this tick starts to act, beyond
    the state's age: 0 for the DSP (it applies a torque when it arrives); one control period
    for CiA 402 cyclic synchronous torque (a drive latches the RPDO at the next SYNC). The
    pacer brings the state and the features forward by it (``controller.predict_state``,
    ``predict_features``)."""
    drives: dict[str, Any] | None = None
    """What the profile's drives reported for this tick, as extra fields of the cycle record
    (the ``drive_*`` fields of ``cycle_schema.json``, one value per joint); None: the profile
    has none (the DSP's drive state is ``drive_mode``)."""


class StopFlag(Protocol):
    """A stop request (``threading.Event``): long waits look at it."""

    def is_set(self) -> bool: ...


class InputJudge(Protocol):
    """How the clock mode judges the inputs' ages (the runtime's pacer is one)."""

    @property
    def state_limit_s(self) -> float:
        """A joint state older than this is stale."""
        ...

    @property
    def status_limit_s(self) -> float | None:
        """A drive status older than this means a silent drive (None: no limit)."""
        ...

    def feature_age_ms(self, feat: FeatureMsg, recv_ns: int, wake_ns: int) -> float:
        """How old ``feat`` (received at ``recv_ns``) is at the tick woken at ``wake_ns``."""
        ...


class HardwareInterface(Protocol):
    """One rig, read and written from the control thread (see the module docstring).

    Every time is on the loop's clock (integer ns). Errors are raised from the package's
    exception tree with a one-line message; nothing here returns a status code to check.
    """

    def configure(self, stop: StopFlag) -> None:
        """Open the links for this run and check the peer: return once it answers (the first
        joint state; with features read by ring, the first features too). Raise when it stays
        silent past the profile's start-up timeout; return at once when ``stop`` is set (the
        caller looks at ``stop`` before activating)."""
        ...

    def activate(self, now_ns: int) -> bool:
        """One step of arming at ``now_ns``: request the drive's enable on the first call,
        keep the command stream cyclic (realtime: called once per period), take the drive's
        statuses. True once armed (the drive reports *operation enabled* and the profile's
        walk is done): the tick of that call, in realtime, is the first law tick. Raises when
        the drive has not enabled within the profile's enable timeout."""
        ...

    def wait_inputs(self, until_ns: int) -> None:
        """Realtime, between releases: take inputs off the links as they arrive until at
        most ``until_ns``, so that :meth:`read` finds them decoded. May return early."""
        ...

    def step(self, timeout_s: float) -> int | None:
        """Lockstep: block until the world is at its next control period and its inputs are
        there; that period's index k (increasing; a gap means skipped periods). None when
        nothing came within ``timeout_s`` (the caller decides whether the run ended)."""
        ...

    def read(self, now_ns: int, judge: InputJudge) -> Observation:
        """The read phase at ``now_ns``: the newest joint state and features, judged stale or
        fresh by ``judge``, and the drive mode of this tick (the drive's statuses followed,
        re-arming by the run's policy)."""
        ...

    def write(self, tau: tuple[float, float], *, sync: int | None, release_ns: int) -> None:
        """The write phase: the tick's torque (N m), answering period ``sync`` in lockstep,
        else carrying how long after ``release_ns`` it left."""
        ...

    def command(self, action: str) -> str | None:
        """An operator's ``arm``, ``disarm`` or ``mark``: None when done, else why not."""
        ...

    def deactivate(self) -> None:
        """Zero torque and disable; stop feeding the run's decoders and hooks (after this no
        callback of the links touches the run). Safe to call when not activated."""
        ...

    def diagnostics(self) -> dict[str, dict[str, Any]]:
        """This run's link and drive counters, one block per component of ``/diagnostics``
        (the DSP profile: ``can_rx``, ``features``, ``dsp``)."""
        ...


__all__ = ["HardwareInterface", "InputJudge", "Observation", "StopFlag"]
