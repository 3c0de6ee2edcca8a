"""The zenoh half of a hardware profile: the image features (and, when logged, the camera's
images) of one run, fed to one :class:`~hal.vision_receivers.FeatureDecoder`.

Realtime: a ring the control thread drains (:meth:`FeatureLink.poll`); lockstep: a callback
feeds each message as it arrives, so a period's tick can wait for the answer to its pose
(:meth:`FeatureLink.wait_pose`). After :meth:`FeatureLink.detach` no callback touches the run
(zenoh may deliver a sample after the undeclare returns, and the run's log is closed next).

A plan's runs share the vision process, so an image the run before still owed may come in the
next run: the next run's link is given those (:meth:`FeatureLink.images_owed`) and keeps such
an image out of its log (``images_of_run_before``)."""

from __future__ import annotations

import contextlib
import math
import threading
from collections.abc import Iterable
from typing import Any

import numpy as np

from hal.errors import HalCodecError
from hal.hardware_interface import InputJudge
from hal.vision_image import decode_vision_image
from hal.vision_receivers import FeatureDecoder
from hal.zenoh_session import KEY_FEATURES, KEY_VISION_IMAGE, PayloadRing
from rt_controller.runtime.context import RunContext
from rt_controller.runtime.recorder import IMAGE


class FeatureLink:
    """The features of one run (see the module docstring)."""

    def __init__(
        self,
        ctx: RunContext,
        session: Any,
        features: FeatureDecoder,
        *,
        by_callback: bool,
        record_raw: bool,
        owed_before: Iterable[int] = (),
    ) -> None:
        """``owed_before``: :meth:`images_owed` of the plan's run before this one."""
        self.ctx = ctx
        self.session = session
        self.features = features
        self.by_callback = by_callback
        self.record_raw = record_raw
        self._ring: PayloadRing | None = None
        self._subscriber: Any = None
        self._image_subscriber: Any = None
        self.images_rejected = 0
        """``hil/vision/image`` payloads refused for the log (not authentic or malformed)."""
        self._images = threading.Condition()
        self._images_due: list[int] = []
        """Simulation times of the frames received whose features said their image follows
        (``FeatureMsg.image``), still to come, oldest first."""
        self._image_seen_ns = -1
        """Simulation time of the newest image logged."""
        self._images_lost = 0
        """Images due that a newer image overtook: the vision process sends them in order on
        one publisher, so an image overtaken never comes (a realtime link dropped it)."""
        self._owed_before = set(owed_before)
        """Simulation times of the images the run before was owed (:meth:`images_owed`)."""
        self._newest_ns = -1
        """Simulation time of the newest features of this run accepted."""
        self.images_of_run_before = 0
        """Images the run before was owed that came in this run, before this run's features
        reached their time: not this run's, so not in its log."""
        self._feeding = threading.Lock()
        self._attached = False
        self._taking_features = True
        """False from :meth:`settle_images` on: the run has ended."""
        self._callback_errors_before = 0
        """The session's ``callback_errors`` when this run attached (a plan's runs share it)."""

    def attach(self) -> None:
        """Subscribe this run to the features (and the camera's images, when logged)."""
        self._attached = True
        self._callback_errors_before = self._session_callback_errors()
        if self.by_callback:
            self._subscriber = self.session.subscribe(KEY_FEATURES, self._on_features)
        else:
            self._ring = self.session.subscribe_ring(KEY_FEATURES)
        if self.ctx.cfg.camera.image_log_fps > 0:
            self._image_subscriber = self.session.subscribe(KEY_VISION_IMAGE, self._on_image)

    def detach(self) -> None:
        """Undeclare the subscriptions; wait for a callback still feeding to finish."""
        if self._ring is not None:
            self._ring.close()
            self._ring = None
        for sub in (self._subscriber, self._image_subscriber):
            if sub is not None:
                with contextlib.suppress(Exception):  # a closed session undeclared it already
                    sub.undeclare()
        self._subscriber = self._image_subscriber = None
        with self._feeding:
            self._attached = False

    def as_dict(self) -> dict[str, int]:
        """The feature decoder's counters plus ``images_rejected``, ``images_missing`` (images
        the received features announced that are not in the log: overtaken by a newer one, or
        still to come) and ``callback_errors`` (messages or images lost to an exception in
        this run's zenoh callbacks, which the session swallows; a bug if not zero): the run's
        diagnostics."""
        with self._images:
            missing = self._images_lost + len(self._images_due)
        return {
            **self.features.counts.as_dict(),
            "images_rejected": self.images_rejected,
            "images_missing": missing,
            "images_of_run_before": self.images_of_run_before,
            "callback_errors": self._session_callback_errors() - self._callback_errors_before,
        }

    def _session_callback_errors(self) -> int:
        """The session's count of exceptions swallowed in its callbacks (0 for a session that
        keeps none, as a test's stand-in)."""
        return int(getattr(self.session, "callback_errors", 0))

    def images_owed(self) -> tuple[int, ...]:
        """Simulation times of the images announced by this run's features that are not in
        its log (for the next run of a plan: ``owed_before``)."""
        with self._images:
            return tuple(self._images_due)

    def settle_images(self, quiet_s: float) -> bool:
        """The run's end: take no more features (the loop is over; one arriving now would
        announce an image after this wait), then wait until the camera images announced by the
        features received so far are in the log (the vision process sends each after its
        features, so the run's last ones may still be on their way), as long as each comes
        within ``quiet_s`` of the one before. True when none is still to come."""
        with self._feeding:
            self._taking_features = False
        with self._images:
            while self._images_due:
                seen = self._image_seen_ns
                if not self._images.wait_for(lambda s=seen: self._image_seen_ns != s, quiet_s):
                    return False
            return True

    def poll(self, now_ns: int) -> None:
        """Realtime: the messages waiting in the ring into the decoder, stamped ``now_ns``."""
        if self._ring is not None:
            for payload in self._ring.drain():
                self._on_features(payload, now_ns)

    def wait_pose(self, seq: int, timeout_s: float) -> bool:
        """Lockstep: until the features answering pose ``seq`` (or newer) arrived."""
        return self.features.wait_pose_seq(seq, timeout_s) is not None

    def latest(self, now_ns: int, judge: InputJudge) -> tuple[np.ndarray, float, bool, bool]:
        """The newest features at ``now_ns``: ``(f, age ms, stale, valid)`` (NaN when none)."""
        feat, recv_ns = self.features.latest_received()
        if feat is None or recv_ns is None:
            return np.full(2, math.nan), math.nan, True, False
        age_ms = judge.feature_age_ms(feat, recv_ns, now_ns)
        timeout_ms = self.ctx.cfg.controller.feature_timeout_s * 1e3
        return np.array(feat.f), age_ms, not (0.0 <= age_ms <= timeout_ms), feat.valid

    def _on_features(self, payload: bytes, now_ns: int | None = None) -> None:
        with self._feeding:
            if not (self._attached and self._taking_features):
                return
            now = self.ctx.clock.now_ns() if now_ns is None else now_ns
            msg = self.features.feed(payload, now)
            if self.record_raw:
                self.ctx.recorder.record_vision(payload, now)
            if msg is not None:
                self._newest_ns = max(self._newest_ns, msg.sim_time_ns)
            if msg is not None and msg.image:
                with self._images:
                    due = self._images_due
                    if msg.sim_time_ns > max(self._image_seen_ns, due[-1] if due else -1):
                        due.append(msg.sim_time_ns)

    def _on_image(self, payload: bytes) -> None:
        """What the camera saw (``hil/vision/image``, authenticated) into the log."""
        with self._feeding:
            if not self._attached:
                return
            try:
                image = decode_vision_image(payload, self.features.key)
            except HalCodecError:
                self.images_rejected += 1
                return
            t = image.sim_time_ns
            if t in self._owed_before and t > self._newest_ns:  # the run before's, late
                self._owed_before.discard(t)
                self.images_of_run_before += 1
                return
            self.ctx.recorder.write(IMAGE, self.ctx.clock.now_ns(), bytes(payload))
        with self._images:
            seen = self._image_seen_ns = max(self._image_seen_ns, image.sim_time_ns)
            due = self._images_due
            self._images_lost += sum(1 for t in due if t < image.sim_time_ns)
            self._images_due = [t for t in due if t > seen]
            self._images.notify_all()


__all__ = ["FeatureLink"]
