"""What the camera saw, drawn with Foxglove's schemas from one ``hil/vision/image`` message
(:mod:`hal.vision_image`): the frame and the detector's result on it.

=========================== ============================= =========================================
topic                       schema (protobuf)             content
=========================== ============================= =========================================
``/camera/image``           ``foxglove.CompressedImage``  the frame (PNG), stamped at its capture
``/camera/detection``       ``foxglove.ImageAnnotations`` the detected centre (green), or why there
                                                          is none (red text)
=========================== ============================= =========================================

With ``camera.model = "image"`` these replace the blank image plane of
:mod:`rt_controller.monitor.scene`; ``/camera/annotations`` (the features the controller used)
and ``/camera/calibration`` stay the scene's. The recorder writes them into the log.
"""

from __future__ import annotations

from typing import Any

from foxglove.messages import (
    CircleAnnotation,
    Color,
    CompressedImage,
    ImageAnnotations,
    Point2,
    TextAnnotation,
    Timestamp,
)

from hal.log_topics import DETECTION_TOPIC, IMAGE_TOPIC
from hal.vision_image import VisionImage, decode_vision_image

SCHEMAS: dict[str, Any] = {IMAGE_TOPIC: CompressedImage, DETECTION_TOPIC: ImageAnnotations}
_GREEN = Color(r=0.2, g=0.9, b=0.3, a=1.0)
_RED = Color(r=0.95, g=0.2, b=0.2, a=1.0)
_BACK = Color(r=0.0, g=0.0, b=0.0, a=0.6)


def _stamp(ns: int) -> Timestamp:
    return Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def view_messages(img: VisionImage, log_time_ns: int) -> list[tuple[str, Any]]:
    """The frame and its detection overlay, stamped ``log_time_ns``."""
    ts = _stamp(log_time_ns)
    image = CompressedImage(timestamp=ts, frame_id="camera", data=img.png, format="png")
    circles, texts = [], []
    if img.valid:
        u, v = img.uv
        circles.append(
            CircleAnnotation(
                timestamp=ts,
                position=Point2(x=u, y=v),
                diameter=8.0,
                thickness=2.0,
                outline_color=_GREEN,
            )
        )
        label, color = f"detected f = ({img.f[0]:.2f}, {img.f[1]:.2f}) px", _GREEN
    else:
        label, color = f"no target: {img.reason}", _RED
    texts.append(
        TextAnnotation(
            timestamp=ts,
            position=Point2(x=8.0, y=20.0),
            text=f"frame {img.frame}: {label}",
            font_size=14.0,
            text_color=color,
            background_color=_BACK,
        )
    )
    return [
        (IMAGE_TOPIC, image),
        (DETECTION_TOPIC, ImageAnnotations(circles=circles, texts=texts)),
    ]


def payload_messages(payload: bytes, mono_to_unix_ns: int) -> tuple[int, list[tuple[str, Any]]]:
    """``(log_time_ns, messages)`` of a raw ``hil/vision/image`` payload: :func:`view_messages`
    at its capture stamp (CLOCK_MONOTONIC shifted by ``mono_to_unix_ns``); raises
    ``HalCodecError`` for a payload that is no vision image."""
    img = decode_vision_image(payload)
    log_time = max(0, img.stamp_ns + mono_to_unix_ns)
    return log_time, view_messages(img, log_time)
