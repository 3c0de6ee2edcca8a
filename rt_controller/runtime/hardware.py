"""The DSP profile of the hardware seam (:class:`hal.hardware_interface.HardwareInterface`):
the emulated or real DSP of ``hal/hil.dbc`` over CAN, the image features over zenoh.

The CAN link is a :class:`~hal.joint_client.JointClient` in poll mode (read in the control
thread, no receive thread); the features come from a zenoh subscription into one decoder: a
ring the control thread drains (realtime), or a callback (lockstep: a period's tick waits for
the answer to its pose). The drive's state is followed by :class:`DrivePolicy`. In lockstep
the DSP paces: :meth:`DspHardware.step` waits for its ``Sync(k)``.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from typing import Any

import numpy as np

from hal.errors import HalCodecError, HalTimeoutError
from hal.hardware_interface import InputJudge, Observation, StopFlag
from hal.joint_client import JointClient
from hal.vision_image import decode_vision_image
from hal.vision_receivers import FeatureDecoder
from hal.zenoh_session import KEY_FEATURES, KEY_VISION_IMAGE, PayloadRing
from rt_controller.errors import ControllerError
from rt_controller.runtime import diagnostics
from rt_controller.runtime.context import RunContext
from rt_controller.runtime.drive_policy import ENABLE_TIMEOUT_S, DrivePolicy
from rt_controller.runtime.pacers import LOCKSTEP_FEATURE_TIMEOUT_S
from rt_controller.runtime.recorder import IMAGE

STARTUP_TIMEOUT_S = 20.0
"""How long start-up waits for the first joint state and features before giving up."""
ARMING_COMMANDS = 8
"""Realtime: zero torques sent while arming, at least: the DSP learns the cycle's phase from the
earliest of its recent commands, so a slow first law frame does not place the scenario's t = 0
late (which would delay every torque of the run by as much)."""
PREFETCH_GUARD_NS = 1_000_000
"""Realtime: the read-ahead between releases stops this long before the next release."""


class DspHardware:
    """CAN and zenoh of one run, read and written from the control thread."""

    def __init__(
        self,
        ctx: RunContext,
        dsp: JointClient,
        session: Any,
        features: FeatureDecoder,
        *,
        lockstep: bool,
        record_raw: bool,
    ) -> None:
        """``session``: the run's zenoh session (``subscribe``, ``subscribe_ring``);
        ``lockstep``: the DSP's Sync paces (features by callback, no cyclic arming)."""
        self.ctx = ctx
        self.dsp = dsp
        self.session = session
        self.features = features
        self.lockstep = lockstep
        self.record_raw = record_raw
        self.drive = DrivePolicy(ctx)
        self.can_base = dsp.stats.e2e.as_dict()
        """The CAN receive counters when this run began (a plan's links outlive its runs)."""
        self._ring: PayloadRing | None = None
        self._subscriber: Any = None
        self._image_subscriber: Any = None
        self.images_recorded = self.images_rejected = 0
        """``hil/vision/image`` payloads logged, and refused (not authentic or malformed)."""
        self._feeding = threading.Lock()
        """Held while a callback feeds a message; :meth:`deactivate` takes it to end the feed."""
        self._attached = False
        self._enable_by: int | None = None
        """Arming: when the DSP must report *operation enabled* (None: not yet activated)."""
        self._arming_sent = 0
        self._states_seen = -1
        self._last_sync: int | None = None
        self.last_tau = (0.0, 0.0)

    # --- lifecycle --------------------------------------------------------------------------
    def configure(self, stop: StopFlag) -> None:
        """Subscribe this run to the features (and the camera's images, when logged), hook
        the raw CAN log, then wait for the DSP's first joint state (and, read by ring, the
        first features)."""
        self._attach()
        self._wait_ready(stop, features=not self.lockstep)

    def activate(self, now_ns: int) -> bool:
        """ENABLE on the first call, then (realtime) a zero torque (Enable = 0) at every call,
        until the DSP reports *operation enabled* and has had ``ARMING_COMMANDS`` of them. The
        command stream is cyclic from ENABLE on (the DSP arms its watchdog there); the zeros
        teach the DSP the cycle's phase, on which the emulated DSP places the scenario's t = 0
        when the first law tick's frame applies torque. Counted in ``arming_ticks``."""
        clock, dsp = self.ctx.clock, self.dsp
        expired = self._enable_by is not None and clock.now_ns() > self._enable_by
        self._poll(clock.now_ns())
        needed = 0 if self.lockstep else ARMING_COMMANDS
        if self.drive.enabled_now(dsp, expired) and self._arming_sent >= needed:
            return True
        if self._enable_by is None:
            dsp.enable()
            self._enable_by = clock.now_ns() + round(ENABLE_TIMEOUT_S * 1e9)
        if not self.lockstep:
            delay = (clock.now_ns() - now_ns) // 1000
            dsp.send_torque(0.0, 0.0, release_delay_us=delay, enable=False)
            self._arming_sent += 1
            self.ctx.counters.arming_ticks += 1
        self._states_seen = dsp.states_received
        return False

    def deactivate(self) -> None:
        """Zero torque and DISABLE when armed; end the feeds and hooks of this run."""
        if self._enable_by is not None:
            self.dsp.send_torque(0.0, 0.0)
            self.dsp.disable()
            self._enable_by = None
        if self._ring is not None:
            self._ring.close()
            self._ring = None
        for sub in (self._subscriber, self._image_subscriber):
            if sub is not None:
                with contextlib.suppress(Exception):  # a closed session undeclared it already
                    sub.undeclare()
        self._subscriber = self._image_subscriber = None
        with self._feeding:  # a callback still running on zenoh's thread finishes first
            self._attached = False
        self.dsp.frame_hook = self.dsp.tx_hook = None

    # --- pacing -----------------------------------------------------------------------------
    def wait_inputs(self, until_ns: int) -> None:
        """Realtime, between releases: block on the CAN socket and decode what arrives, so the
        tick finds it decoded; no decode starts within ``PREFETCH_GUARD_NS`` (at most a
        quarter period) of ``until_ns``."""
        now = self.ctx.clock.now_ns()
        guard_ns = min(PREFETCH_GUARD_NS, self.ctx.cfg.rates.control_period_ns // 4)
        stop_ns = until_ns - guard_ns
        if now >= stop_ns:
            time.sleep(max(0, until_ns - now) / 1e9)
        elif self.dsp.wait_readable((stop_ns - now) / 1e9):
            self._poll(self.ctx.clock.now_ns())

    def step(self, timeout_s: float) -> int | None:
        """Lockstep: the next new ``Sync(k)`` of the DSP (a re-sent one, whose command was
        lost, gets the last torque again), then the features answering pose k; k, or None
        when no Sync came within ``timeout_s``."""
        while True:
            try:
                k = self.dsp.wait_sync(timeout_s)
            except HalTimeoutError:
                return None
            last = self._last_sync
            if last is None or k > last:
                break
            if k == last:  # a re-sent Sync: our command was lost, send it again
                self.dsp.send_torque(*self.last_tau, tick=k)
        self._last_sync = k
        self.features.wait_pose_seq(k, LOCKSTEP_FEATURE_TIMEOUT_S)
        return k

    # --- read and write ---------------------------------------------------------------------
    def read(self, now_ns: int, judge: InputJudge) -> Observation:
        """Everything waiting on the links taken off, the drive state followed to ``now_ns``,
        the newest joint state and features judged stale or fresh by ``judge``."""
        self._poll(self.ctx.clock.now_ns())  # stamped when actually read, not at the wake-up
        dsp = self.dsp
        state_new = dsp.states_received != self._states_seen
        self._states_seen = dsp.states_received
        mode = self.drive.follow(dsp, now_ns, judge.status_limit_s)
        state_stale, state_ns = False, None
        try:
            state = dsp.latest_state(max_age_s=judge.state_limit_s, now_ns=now_ns)
            q, dq, state_ns = np.array(state.q), np.array(state.dq), state.t_ns
            state_age_ms = (now_ns - state.t_ns) / 1e6
        except HalTimeoutError:
            state_stale, q, dq, state_age_ms = True, np.full(2, math.nan), np.zeros(2), math.nan
        feat, recv_ns = self.features.latest_received()
        if feat is None or recv_ns is None:
            f, f_age_ms = np.full(2, math.nan), math.nan
        else:
            f, f_age_ms = np.array(feat.f), judge.feature_age_ms(feat, recv_ns, now_ns)
        timeout_ms = self.ctx.cfg.controller.feature_timeout_s * 1e3
        return Observation(
            q=q,
            dq=dq,
            f=f,
            state_ns=state_ns,
            state_age_ms=state_age_ms,
            state_stale=state_stale,
            f_age_ms=f_age_ms,
            f_stale=not (0.0 <= f_age_ms <= timeout_ms),
            f_valid=feat is not None and feat.valid,
            drive_mode=mode,
            state_new=state_new,
        )

    def write(self, tau: tuple[float, float], *, sync: int | None, release_ns: int) -> None:
        """Send the tick's torque: answering Sync ``sync`` when given, else carrying how long
        after its release it left (realtime, ``TorqueCommand.Tick``)."""
        t1, t2 = self.last_tau = tau
        if sync is not None:
            self.dsp.send_torque(t1, t2, tick=sync)
        else:
            delay = (self.ctx.clock.now_ns() - release_ns) // 1000
            self.dsp.send_torque(t1, t2, release_delay_us=delay)

    def command(self, action: str) -> str | None:
        """An operator's ``arm``, ``disarm`` or ``mark`` (:meth:`DrivePolicy.operate`)."""
        return self.drive.operate(self.dsp, action)

    def diagnostics(self) -> dict[str, dict[str, Any]]:
        """The receive verdicts of this run (``can_rx``, ``features``) and the drive (``dsp``)."""
        return {
            "can_rx": diagnostics.since(self.can_base, self.dsp.stats.e2e.as_dict()),
            "features": self.features.counts.as_dict(),
            "dsp": self.drive.block(self.dsp),
        }

    # --- links ------------------------------------------------------------------------------
    def _attach(self) -> None:
        self._attached = True
        session, rec = self.session, self.ctx.recorder
        if self.lockstep:
            self._subscriber = session.subscribe(KEY_FEATURES, self._on_features)
        else:
            self._ring = session.subscribe_ring(KEY_FEATURES)
        if self.ctx.cfg.camera.image_log_fps > 0:
            self._image_subscriber = session.subscribe(KEY_VISION_IMAGE, self._on_image)
        if self.record_raw:
            now = self.ctx.clock.now_ns
            self.dsp.frame_hook = lambda m: rec.record_can(m, now(), "rx")
            self.dsp.tx_hook = lambda m: rec.record_can(m, now(), "tx")

    def _wait_ready(self, stop: StopFlag, *, features: bool) -> None:
        """Until the first joint state (and, with ``features``, image features)."""
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not stop.is_set():
            self._poll(self.ctx.clock.now_ns())
            have_state = self.dsp.state_age_s() is not None
            if have_state and (not features or self.features.latest is not None):
                return
            if time.monotonic() > deadline:
                missing = "joint state (CAN)" if not have_state else "image features (zenoh)"
                raise ControllerError(
                    f"no {missing} within {STARTUP_TIMEOUT_S:.0f} s: is `hil emulator` "
                    f"(and `hil vision`) running on the same transports?"
                )
            self.ctx.pause(10_000_000)

    def _poll(self, now_ns: int) -> None:
        """Take every CAN frame waiting on the bus and the newest feature messages off the
        transports, into their decoders (stamped ``now_ns`` where the clock has no kernel
        stamps)."""
        self.dsp.drain(now_ns, timestamps=self.ctx.clock.kernel_stamps)
        if self._ring is not None:
            for payload in self._ring.drain():
                self._on_features(payload, now_ns)

    def _on_features(self, payload: bytes, now_ns: int | None = None) -> None:
        """One feature message into the decoder and the log; none after :meth:`deactivate`
        (zenoh may still deliver a sample after the undeclare returns, and the run's log is
        closed next)."""
        with self._feeding:
            if not self._attached:
                return
            now = self.ctx.clock.now_ns() if now_ns is None else now_ns
            self.features.feed(payload, now)
            if self.record_raw:
                self.ctx.recorder.record_vision(payload, now)

    def _on_image(self, payload: bytes) -> None:
        """What the camera saw (``hil/vision/image``, authenticated) into the log."""
        with self._feeding:
            if not self._attached:
                return
            try:
                decode_vision_image(payload, self.features.key)
            except HalCodecError:
                self.images_rejected += 1
                return
            self.images_recorded += 1
            self.ctx.recorder.write(IMAGE, self.ctx.clock.now_ns(), bytes(payload))


__all__ = ["STARTUP_TIMEOUT_S", "DspHardware"]
