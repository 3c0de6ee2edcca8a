"""Emulator side of the vision link: publishes the camera pose on ``hil/emulator/camera_pose``.

Protocol (see :mod:`plant_emulator.vision_node`):

* **lockstep** — publish exactly one pose per control period, ``seq`` = the control tick k, just
  *before* the CAN ``Sync`` frame of tick k. The vision process answers every such pose with one
  features message carrying ``pose_seq = k``; the controller waits for it before computing tick k.
  Call :meth:`PosePublisher.wait_for_subscribers` before the first lockstep pose.
* **realtime** — publish poses at the physics or joint-state rate (at least the camera frame rate);
  the vision process samples the newest one on its own frame clock.

The publisher blocks rather than drops when the link is congested (see
:meth:`hal.zenoh_session.ZenohSession.publisher`).
"""

from __future__ import annotations

import contextlib
import secrets
import sys
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import zenoh

from hal.errors import HalTransportError
from hal.vision_codec import PoseMsg, encode_pose
from hal.zenoh_session import KEY_CAMERA_POSE, ZenohSession
from plant_emulator.camera import CameraPose

if TYPE_CHECKING:
    from plant_emulator.camera_node import CameraNode


class PosePublisher:
    """Publishes camera poses; one per emulator run (its random ``source`` id marks the run)."""

    def __init__(
        self, session: ZenohSession, *, source: int | None = None, key: bytes | None = None
    ) -> None:
        self.session = session
        self.key = key
        """Rig key the poses are authenticated with (None: this process's ephemeral key)."""
        self.source = secrets.randbits(32) if source is None else source
        self.seed: int | None = None
        """The camera noise seed the poses name (set by a scenario reset that named one; None:
        the vision process uses its own ``camera.seed``)."""
        self.published = 0
        self.errors = 0
        self._pub = session.publisher(KEY_CAMERA_POSE)

    def publish(
        self,
        seq: int,
        sim_time_ns: int,
        pose: CameraPose,
        lockstep: bool,
        stamp_ns: int | None = None,
    ) -> None:
        """Send one pose (``stamp_ns`` defaults to ``time.monotonic_ns()`` now).

        Raises :class:`HalTransportError` if the session is closed or broken.
        """
        msg = PoseMsg(
            seq,
            sim_time_ns,
            time.monotonic_ns() if stamp_ns is None else stamp_ns,
            float(pose.x),
            float(pose.y),
            float(pose.phi),
            lockstep,
            self.source,
            self.seed,
        )
        payload = encode_pose(msg, self.key)
        try:
            self._pub.put(payload)
        except zenoh.ZError as exc:
            self.errors += 1
            raise HalTransportError(f"zenoh: cannot publish camera pose: {exc}") from exc
        self.published += 1

    def has_subscribers(self) -> bool:
        """Whether a vision process currently listens for poses."""
        return self.session.has_subscriber(self._pub)

    def wait_for_subscribers(
        self, timeout_s: float, stop_event: threading.Event | None = None
    ) -> bool:
        """Wait until a vision process subscribes (call before the first lockstep pose)."""
        return self.session.has_subscriber(self._pub, timeout_s, stop_event)

    def close(self) -> None:
        """Undeclare the publisher (the session stays open). Idempotent."""
        with contextlib.suppress(zenoh.ZError):
            self._pub.undeclare()


class PoseLink:
    """An emulator's pose sink (both profiles): each pose to the emulated camera in this
    process, if any, and on zenoh; a broken session is counted, never fatal."""

    def __init__(self, publisher: PosePublisher) -> None:
        self.publisher = publisher
        self.errors = 0
        self.camera: CameraNode | None = None
        """The emulated camera (``camera.model = "image"``), offered every pose."""

    def __call__(
        self,
        seq: int,
        sim_time_ns: int,
        pose: CameraPose,
        lockstep: bool,
        stamp_ns: int | None = None,
    ) -> None:
        """One pose (:meth:`PosePublisher.publish`'s arguments)."""
        if self.camera is not None:
            self.camera.offer(seq, sim_time_ns, pose, lockstep, stamp_ns)
        try:
            self.publisher.publish(seq, sim_time_ns, pose, lockstep, stamp_ns)
        except HalTransportError as exc:
            self.errors += 1
            if self.errors == 1:
                print(f"hil emulator: warning: {exc} (further errors counted)", file=sys.stderr)

    def new_run(self, seed: int | None) -> None:
        """A scenario reset: later poses carry a new source id, so the vision process starts a
        new run (frame counter, clocks, noise generator) as for a new emulator, and the seed the
        reset named (None: the vision process's own ``camera.seed``)."""
        old = self.publisher.source
        while self.publisher.source == old:
            self.publisher.source = secrets.randbits(32)
        self.publisher.seed = seed
        if self.camera is not None:
            self.camera.new_run(seed)


def wait_until(
    predicate: Callable[[], bool], timeout_s: float, stop_event: threading.Event | None = None
) -> bool:
    """Poll ``predicate`` every 5 ms until it holds (True), ``timeout_s`` passes or
    ``stop_event`` is set (False)."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() >= deadline or (stop_event is not None and stop_event.is_set()):
            return False
        time.sleep(0.005)
    return True
