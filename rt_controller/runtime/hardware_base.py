"""What every hardware profile of the seam (:class:`hal.hardware_interface.HardwareInterface`)
does the same way, written once: the zenoh half (a :class:`~rt_controller.runtime.feature_link.
FeatureLink`), the raw CAN log's hooks, the arming deadline, the late-state mark, the
silent-drive rule, the tick's :class:`~hal.hardware_interface.Observation` and deactivation.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hal.can_tap import FrameTap
from hal.drive_state import MODE_ENABLED, MODE_NO_STATUS
from hal.hardware_interface import InputJudge, Observation
from rt_controller.runtime.context import RunContext
from rt_controller.runtime.feature_link import FeatureLink

IMAGES_SETTLE_S = 2.0
"""How long the end of a run waits for the next camera image of its last frames (it waits on
while they keep coming: the vision process may be far behind)."""
ENABLE_TIMEOUT_S = 5.0
"""How long arming may take until the drive reports *operation enabled*."""
NOTICE_AFTER_S = 2.0
"""How long start-up waits for its inputs before it says what for (``RunContext.say``)."""


class HardwareBase:
    """The shared part of a profile (the DSP's :mod:`~rt_controller.runtime.hardware`, CiA
    402's :mod:`~rt_controller.runtime.cia402_hardware`), which adds how its links arm, read,
    write and disarm."""

    def __init__(
        self, ctx: RunContext, features: FeatureLink, *, lockstep: bool, record_raw: bool
    ) -> None:
        """``lockstep``: the world steps per period (features by callback, no cyclic arming);
        ``record_raw``: every CAN frame sent and received goes to the log's ``/hal/can/*``."""
        self.ctx = ctx
        self.features = features
        self.lockstep = lockstep
        self.record_raw = record_raw
        self._enable_by: int | None = None
        """Arming: when the drive must report *operation enabled* (None: not activated)."""
        self._hooked: FrameTap | None = None
        """The link whose ``rx_hook`` and ``tx_hook`` log the raw frames."""
        self._hook_errors_before = 0
        self._marker = 0

    def why_silent(self) -> str:
        """A hint for a lockstep world that stopped stepping (appended to the end reason)."""
        return ""

    # --- lifecycle --------------------------------------------------------------------------
    def deactivate(self) -> None:
        """Disarm when armed (``_disarm``); end the feeds and hooks of this run, so no callback
        of the links touches it afterwards. Frames the hooks failed to log count in the
        recorder's ``dropped``."""
        if self._enable_by is not None:
            self._disarm()
            self._enable_by = None
        self.features.settle_images(IMAGES_SETTLE_S)  # the images of its last frames
        self.features.detach()
        if self._hooked is not None:
            link, self._hooked = self._hooked, None
            link.rx_hook = link.tx_hook = None
            # a frame whose hook raised is not in the log: a lost record (the run not clean)
            self.ctx.recorder.dropped += link.hook_errors - self._hook_errors_before

    # --- for the profiles -------------------------------------------------------------------
    def _hook_raw_can(self, link: FrameTap) -> None:
        """With ``record_raw``, ``link``'s ``rx_hook`` and ``tx_hook`` log every frame it
        receives and sends (unhooked by :meth:`deactivate`)."""
        if self.record_raw:
            rec, now = self.ctx.recorder, self.ctx.clock.now_ns
            link.rx_hook = lambda m: rec.record_can(m, now(), "rx")
            link.tx_hook = lambda m: rec.record_can(m, now(), "tx")
            self._hooked, self._hook_errors_before = link, link.hook_errors

    def _start_arming(self) -> None:
        """The first arming step: the drive must be enabled ``ENABLE_TIMEOUT_S`` from now."""
        self._enable_by = self.ctx.clock.now_ns() + round(ENABLE_TIMEOUT_S * 1e9)

    def _arrived(self, marker: int) -> bool:
        """Whether ``marker`` (the joint states' count or period) moved since the last call
        (False: the tick found no new state, a ``late_states`` tick)."""
        new, self._marker = marker != self._marker, marker
        return new

    def _tick_mode(self, mode: str, silent: bool) -> str:
        """The tick's drive mode: ``no_status`` for a ``silent`` drive (its last word no longer
        counts); counted in ``drive_ticks`` unless *operation enabled* (no law runs then)."""
        if silent:
            mode = MODE_NO_STATUS
        if mode != MODE_ENABLED:
            self.ctx.counters.drive_ticks[mode] += 1
        return mode

    def _observation(
        self,
        now_ns: int,
        judge: InputJudge,
        state: Any,
        state_ns: int | None,
        age_ms: float,
        mode: str,
        state_new: bool,
        **extra: Any,
    ) -> Observation:
        """The tick's observation: ``state`` (its ``q``, ``dq``; None when stale: NaN
        positions, zero velocities) sampled at ``state_ns``, ``age_ms`` old; the newest
        features judged by ``judge``; the profile's actuation delay; ``extra`` fields."""
        stale = state is None
        f, f_age_ms, f_stale, f_valid = self.features.latest(now_ns, judge)
        return Observation(
            q=np.full(2, math.nan) if stale else np.array(state.q),
            dq=np.zeros(2) if stale else np.array(state.dq),
            f=f,
            state_ns=None if stale else state_ns,
            state_age_ms=age_ms,
            state_stale=stale,
            f_age_ms=f_age_ms,
            f_stale=f_stale,
            f_valid=f_valid,
            drive_mode=mode,
            state_new=state_new,
            actuation_delay_ms=self._actuation_delay_ms(),
            **extra,
        )

    def _actuation_delay_ms(self) -> float:
        """:attr:`Observation.actuation_delay_ms`: none, the torque acts when it arrives."""
        return 0.0

    def _disarm(self) -> None:
        """Given by each profile: at deactivation, torque off and the drive disabled."""
        raise NotImplementedError


__all__ = ["ENABLE_TIMEOUT_S", "HardwareBase"]
