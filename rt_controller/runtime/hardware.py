"""The rig's hardware behind one interface, as ros2_control's hardware interface: ``read``
gives the tick's :class:`Observation` (CAN joint state and DSP status, zenoh image features,
each judged stale or fresh), ``write`` sends the torque. The links are a
:class:`~hal.joint_client.JointClient` in poll mode (read in the control thread, no receive
thread) and the features of a zenoh subscription, fed to one decoder."""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from hal.config import RigConfig
from hal.errors import HalCodecError, HalTimeoutError
from hal.hardware_interface import Observation
from hal.joint_client import JointClient
from hal.vision_codec import FeatureDecoder, FeatureMsg
from hal.vision_image import decode_vision_image
from hal.zenoh_session import KEY_FEATURES, KEY_VISION_IMAGE, PayloadRing
from rt_controller.errors import ControllerError
from rt_controller.runtime import diagnostics
from rt_controller.runtime.cadence import Clock
from rt_controller.runtime.recorder import IMAGE

STARTUP_TIMEOUT_S = 20.0
"""How long start-up waits for the first joint state and features before giving up."""

FeatureAge = Callable[[FeatureMsg, int, int], float]
"""How old a feature message is at a tick, in ms: ``(message, receive ns, wake ns)``; the
pacer knows how (in real time, or in the simulation time of a Sync-paced run)."""


class RigHardware:
    """CAN and zenoh of one run, read and written from the control thread."""

    def __init__(
        self,
        cfg: RigConfig,
        dsp: JointClient,
        features: FeatureDecoder,
        clock: Clock,
        *,
        recorder: Any,
        record_raw: bool,
        kernel_stamps: bool,
    ) -> None:
        """``kernel_stamps``: stamp CAN frames with the kernel's receive time (the real clock;
        a fake clock stamps them when read)."""
        self.cfg = cfg
        self.dsp = dsp
        self.features = features
        self.clock = clock
        self.recorder = recorder
        self.record_raw = record_raw
        self.kernel_stamps = kernel_stamps
        self.can_base = dsp.stats.e2e.as_dict()
        """The CAN receive counters when this run began (a plan's links outlive its runs)."""
        self._ring: PayloadRing | None = None
        self._subscriber: Any = None
        self._image_subscriber: Any = None
        self.images_recorded = self.images_rejected = 0
        """``hil/vision/image`` payloads logged, and refused (not authentic or malformed)."""
        self._feeding = threading.Lock()
        """Held while a callback feeds a message; :meth:`detach` takes it to end the feed."""
        self._attached = False
        self.last_tau = (0.0, 0.0)

    # --- links ------------------------------------------------------------------------------
    def attach(self, session: Any, *, callback: bool) -> None:
        """Subscribe to the features: into a ring this thread drains (``callback=False``), or
        fed as they arrive (a tick that waits for its pose's answer)."""
        self._attached = True
        if callback:
            self._subscriber = session.subscribe(KEY_FEATURES, self._on_features)
        else:
            self._ring = session.subscribe_ring(KEY_FEATURES)
        if self.cfg.camera.image_log_fps > 0:
            self._image_subscriber = session.subscribe(KEY_VISION_IMAGE, self._on_image)
        if self.record_raw:
            rec, now = self.recorder, self.clock.now_ns
            self.dsp.frame_hook = lambda m: rec.record_can(m, now(), "rx")
            self.dsp.tx_hook = lambda m: rec.record_can(m, now(), "tx")

    def detach(self) -> None:
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

    def _on_features(self, payload: bytes, now_ns: int | None = None) -> None:
        """One feature message into the decoder and the log; none once detached (zenoh may
        still deliver a sample after the undeclare returns, and the run's log is closed next)."""
        with self._feeding:
            if not self._attached:
                return
            now = self.clock.now_ns() if now_ns is None else now_ns
            self.features.feed(payload, now)
            if self.record_raw:
                self.recorder.record_vision(payload, now)

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
            self.recorder.write(IMAGE, self.clock.now_ns(), bytes(payload))

    def poll(self, now_ns: int) -> None:
        """Take every CAN frame waiting on the bus and the newest feature messages off the
        transports, into their decoders (stamped ``now_ns`` where the kernel gave no stamp)."""
        self.dsp.drain(now_ns, timestamps=self.kernel_stamps)
        if self._ring is not None:
            for payload in self._ring.drain():
                self._on_features(payload, now_ns)

    def wait_ready(self, stop: Any, *, features: bool, pause: Callable[[int], None]) -> None:
        """Start-up: until the first joint state (and, with ``features``, image features)."""
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not stop.is_set():
            self.poll(self.clock.now_ns())
            have_state = self.dsp.state_age_s() is not None
            if have_state and (not features or self.features.latest is not None):
                return
            if time.monotonic() > deadline:
                missing = "joint state (CAN)" if not have_state else "image features (zenoh)"
                raise ControllerError(
                    f"no {missing} within {STARTUP_TIMEOUT_S:.0f} s: is `hil emulator` "
                    f"(and `hil vision`) running on the same transports?"
                )
            pause(10_000_000)

    # --- read and write ---------------------------------------------------------------------
    def read(
        self, wake_ns: int, *, state_limit_s: float, feature_age: FeatureAge, drive_mode: str
    ) -> Observation:
        """The newest joint state and features (already taken off the transports by
        :meth:`poll`), judged stale or not, with the tick's drive mode."""
        state_stale, state_ns = False, None
        try:
            state = self.dsp.latest_state(max_age_s=state_limit_s, now_ns=wake_ns)
            q, dq, state_ns = np.array(state.q), np.array(state.dq), state.t_ns
            state_age_ms = (wake_ns - state.t_ns) / 1e6
        except HalTimeoutError:
            state_stale, q, dq, state_age_ms = True, np.full(2, math.nan), np.zeros(2), math.nan
        feat, recv_ns = self.features.latest_received()
        if feat is None or recv_ns is None:
            f, f_age_ms = np.full(2, math.nan), math.nan
        else:
            f, f_age_ms = np.array(feat.f), feature_age(feat, recv_ns, wake_ns)
        return Observation(
            q=q,
            dq=dq,
            f=f,
            state_ns=state_ns,
            state_age_ms=state_age_ms,
            state_stale=state_stale,
            f_age_ms=f_age_ms,
            f_stale=not (0.0 <= f_age_ms <= self.cfg.controller.feature_timeout_s * 1e3),
            f_valid=feat is not None and feat.valid,
            drive_mode=drive_mode,
        )

    def write(self, tau: tuple[float, float], *, sync: int | None, release_ns: int) -> int:
        """Send the tick's torque: answering Sync ``sync`` when given, else carrying how long
        after its release it left (realtime, ``TorqueCommand.Tick``); returns that delay in
        microseconds (0 for a Sync answer)."""
        t1, t2 = self.last_tau = tau
        if sync is not None:
            self.dsp.send_torque(t1, t2, tick=sync)
            return 0
        delay = (self.clock.now_ns() - release_ns) // 1000
        self.dsp.send_torque(t1, t2, release_delay_us=delay)
        return delay

    def resend(self, sync: int) -> None:
        """Send the last torque again for a re-sent Sync (the command was lost)."""
        self.dsp.send_torque(*self.last_tau, tick=sync)

    def stop_torque(self) -> None:
        """Zero torque and DISABLE: the end of every run."""
        self.dsp.send_torque(0.0, 0.0)
        self.dsp.disable()

    def counters(self) -> dict[str, dict[str, Any]]:
        """The receive verdicts of this run (``can_rx``, ``features``) for ``/diagnostics``."""
        return {
            "can_rx": diagnostics.since(self.can_base, self.dsp.stats.e2e.as_dict()),
            "features": self.features.counts.as_dict(),
        }
