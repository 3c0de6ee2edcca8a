"""The emulated camera on zenoh: its frame publisher (``hil/camera/frame``) and
:func:`start_camera`, which wires a :class:`~plant_emulator.camera_node.CameraNode` to a
session (frames out, the grabber's region requests in) for both emulator profiles."""

from __future__ import annotations

import contextlib

import zenoh

from hal.config import RigConfig, image_noise_error
from hal.errors import HalConfigError, HalTransportError
from hal.zenoh_session import KEY_CAMERA_FRAME, KEY_CAMERA_ROI, ZenohSession
from plant_emulator.camera_node import CameraNode


class FramePublisher:
    """``hil/camera/frame`` on a zenoh session. Priority ``INTERACTIVE_HIGH``, below the
    ``REAL_TIME`` of the rig's small messages (poses, features), so a 300 kB frame never
    queues ahead of them; blocking (late, never lost: a lost lockstep frame stalls a period)."""

    def __init__(self, session: ZenohSession) -> None:
        self._session = session
        self._pub = session.publisher(KEY_CAMERA_FRAME, priority=zenoh.Priority.INTERACTIVE_HIGH)

    def put(self, payload: bytes) -> None:
        try:
            self._pub.put(payload)
        except zenoh.ZError as exc:
            raise HalTransportError(f"zenoh: cannot publish a camera frame: {exc}") from exc

    def has_subscribers(self) -> bool:
        """Whether a frame grabber (the vision process) currently listens."""
        return self._session.has_subscriber(self._pub)

    def close(self) -> None:
        """Undeclare the publisher (the session stays open). Idempotent."""
        with contextlib.suppress(zenoh.ZError):
            self._pub.undeclare()


def start_camera(
    cfg: RigConfig, session: ZenohSession, stack: contextlib.ExitStack, key: bytes
) -> tuple[CameraNode, FramePublisher]:
    """The emulated camera of ``cfg`` on ``session``: its frame publisher and its node, started;
    both closed by ``stack`` (the emulator's, DSP and CiA 402 profiles alike).
    :class:`~hal.errors.HalConfigError` when ``cfg`` asks for a pixel noise it cannot apply
    (:func:`~hal.config.image_noise_error`)."""
    problem = image_noise_error(cfg)
    if problem is not None:
        raise HalConfigError(problem)
    frames = FramePublisher(session)
    stack.callback(frames.close)
    camera = CameraNode(cfg, frames.put, key=key, watched=frames.has_subscribers)
    stack.callback(camera.close)
    camera.start()
    requests = session.subscribe(KEY_CAMERA_ROI, camera.request)

    def undeclare() -> None:
        with contextlib.suppress(zenoh.ZError):
            requests.undeclare()

    stack.callback(undeclare)
    return camera, frames
