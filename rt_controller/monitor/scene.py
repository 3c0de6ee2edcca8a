"""The arm drawn with Foxglove's own schemas, from one ``/controller/cycle`` record.

One function, :func:`scene_messages`, turns a cycle record (``q``, ``f``, ``tick``) into the
messages of the scene topics; the recorder writes them into the MCAP and ``hil monitor`` sends
them live, so a log and a live connection show the same picture (``foxglove/layout.json``).

============================ ============================== ====================================
topic                        schema (protobuf)              content
============================ ============================== ====================================
``/tf``                      ``foxglove.FrameTransforms``   world -> link1 -> link2 -> camera
``/scene/arm``               ``foxglove.SceneUpdate``       links, joints, frustum, target, ray
``/camera/calibration``      ``foxglove.CameraCalibration`` pinhole of ``camera.s_lambda`` px
                                                            (on images: the true lens)
``/camera/annotations``      ``foxglove.ImageAnnotations``  features f, image centre (f = 0)
``/camera/image``            ``foxglove.CompressedImage``   a blank image plane (PNG, ~1 Hz)
============================ ============================== ====================================

Geometry (the paper's eq. 6): the arm moves in the plane z = 0 of frame ``world``; the camera
sits at the tip of link 2 with its optical axis along +z, image x along the hand, image y to its
left; the target lies in the plane z = ``camera.z_wo``. The target drawn is the point the camera
sees at ``f`` (inverse of eq. 6): ``p = p_c + R(phi) f / gain``. Image pixel = centre + f.
"""

from __future__ import annotations

import math
import struct
import zlib
from typing import Any

from foxglove.messages import (
    ArrowPrimitive,
    CameraCalibration,
    CircleAnnotation,
    Color,
    CompressedImage,
    CubePrimitive,
    FrameTransform,
    FrameTransforms,
    ImageAnnotations,
    KeyValuePair,
    LinePrimitive,
    LinePrimitiveLineType,
    Point2,
    Point3,
    PointsAnnotation,
    PointsAnnotationType,
    Pose,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    TextAnnotation,
    Timestamp,
    Vector3,
)

from hal.config import RigConfig
from hal.log_topics import (
    ANNOTATIONS_TOPIC,
    CALIBRATION_TOPIC,
    IMAGE_TOPIC,
    SCENE_TOPIC,
    TF_TOPIC,
)

WORLD, LINK1, LINK2, CAMERA = "world", "link1", "link2", "camera"
SCENE_MAX_HZ = 50.0
"""The scene is drawn for every tick up to this rate, for every n-th tick above it."""
IMAGE_WIDTH, IMAGE_HEIGHT = 640, 480
"""The image plane drawn (px); features are offsets from its centre."""

SCHEMAS: dict[str, Any] = {
    TF_TOPIC: FrameTransforms,
    SCENE_TOPIC: SceneUpdate,
    CALIBRATION_TOPIC: CameraCalibration,
    ANNOTATIONS_TOPIC: ImageAnnotations,
    IMAGE_TOPIC: CompressedImage,
}
"""Scene topic -> foxglove message class (``.get_schema()`` gives its protobuf schema)."""

_GREY = Color(r=0.6, g=0.6, b=0.65, a=1.0)
_BLUE = Color(r=0.2, g=0.45, b=0.9, a=1.0)
_ORANGE = Color(r=1.0, g=0.55, b=0.1, a=1.0)
_RED = Color(r=0.9, g=0.15, b=0.15, a=1.0)
_GREEN = Color(r=0.2, g=0.8, b=0.3, a=1.0)
_WHITE = Color(r=1.0, g=1.0, b=1.0, a=1.0)


def _stamp(log_time_ns: int) -> Timestamp:
    return Timestamp(sec=log_time_ns // 1_000_000_000, nsec=log_time_ns % 1_000_000_000)


def _yaw(angle: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(angle / 2), w=math.cos(angle / 2))


def blank_png(width: int, height: int, level: int = 24) -> bytes:
    """A uniform grey 8-bit PNG (a few hundred bytes): the image plane the annotations go on."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    raw = (b"\x00" + bytes([level]) * width) * height
    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw, 9))
        + chunk(b"IEND", b"")
    )


def _finite2(v: Any) -> tuple[float, float] | None:
    try:
        a, b = float(v[0]), float(v[1])
    except (TypeError, ValueError, IndexError):
        return None
    return (a, b) if math.isfinite(a) and math.isfinite(b) else None


class SceneBuilder:
    """Builds the scene messages of a cycle record for one rig configuration.

    :meth:`messages` returns ``[(topic, message), ...]`` (foxglove-sdk message objects; ``encode()``
    gives the protobuf bytes). A record without finite ``q`` draws nothing.
    """

    def __init__(self, cfg: RigConfig) -> None:
        self.l1, self.l2 = cfg.robot.l1, cfg.robot.l2
        self.gain = cfg.camera.gain
        self.focal = cfg.camera.s_lambda
        self.depth = cfg.camera.z_wo
        self.cx, self.cy = IMAGE_WIDTH / 2, IMAGE_HEIGHT / 2
        self.every = max(1, math.ceil(cfg.rates.control_hz / SCENE_MAX_HZ - 1e-9))
        """Draw the ticks whose number is a multiple of this (both the log and the live view)."""
        self.image_every = max(1, round(cfg.rates.control_hz))
        """The background image goes with every ``image_every``-th tick (about 1 Hz)."""
        self._png = blank_png(IMAGE_WIDTH, IMAGE_HEIGHT)
        self.blank_image = cfg.camera.model != "image"
        """The blank plane only without frames: on images the camera's own frames are
        ``/camera/image`` (:mod:`rt_controller.monitor.camera_view`)."""
        self.size = (IMAGE_WIDTH, IMAGE_HEIGHT)
        self.focal_xy = (self.focal, self.focal)
        self.dist = [0.0] * 5
        if not self.blank_image:  # the emulated camera's true intrinsics and lens
            cam = cfg.camera
            self.size = (cam.width_px, cam.height_px)
            self.focal_xy = cam.true_focal_px
            self.cx, self.cy = cam.true_principal_point_px
            self.dist = list(cam.true_lens)

    @staticmethod
    def schemas() -> dict[str, Any]:
        """Scene topic -> foxglove message class."""
        return dict(SCHEMAS)

    # --- geometry -----------------------------------------------------------------------------
    def camera_pose(self, q: tuple[float, float]) -> tuple[float, float, float]:
        """Forward kinematics of the hand: camera position (m) and heading q1 + q2 (rad)."""
        a12 = q[0] + q[1]
        x = self.l1 * math.cos(q[0]) + self.l2 * math.cos(a12)
        y = self.l1 * math.sin(q[0]) + self.l2 * math.sin(a12)
        return x, y, a12

    def target(self, pose: tuple[float, float, float], f: tuple[float, float]) -> tuple[float, ...]:
        """The point of the target plane that a camera at ``pose`` sees at ``f`` (eq. 6)."""
        x, y, phi = pose
        c, s = math.cos(phi), math.sin(phi)
        fx, fy = f[0] / self.gain, f[1] / self.gain
        return (x + c * fx - s * fy, y + s * fx + c * fy, self.depth)

    # --- messages -----------------------------------------------------------------------------
    def messages(self, record: dict[str, Any], log_time_ns: int) -> list[tuple[str, Any]]:
        q = _finite2(record.get("q"))
        if q is None:
            return []
        f = _finite2(record.get("f"))
        k = record.get("tick")
        tick = str(k)
        ts = _stamp(log_time_ns)
        out = [
            (TF_TOPIC, self.transforms(q, ts)),
            (SCENE_TOPIC, self.scene(q, f, ts, tick)),
            (CALIBRATION_TOPIC, self.calibration(ts)),
            (ANNOTATIONS_TOPIC, self.annotations(f, ts, tick)),
        ]
        if self.blank_image and isinstance(k, int) and k % self.image_every == 0:
            out.append((IMAGE_TOPIC, self.image(ts)))
        return out

    def transforms(self, q: tuple[float, float], ts: Timestamp) -> FrameTransforms:
        def tf(parent: str, child: str, x: float, angle: float) -> FrameTransform:
            return FrameTransform(
                timestamp=ts,
                parent_frame_id=parent,
                child_frame_id=child,
                translation=Vector3(x=x, y=0.0, z=0.0),
                rotation=_yaw(angle),
            )

        return FrameTransforms(
            transforms=[
                tf(WORLD, LINK1, 0.0, q[0]),
                tf(LINK1, LINK2, self.l1, q[1]),
                tf(LINK2, CAMERA, self.l2, 0.0),
            ]
        )

    def scene(
        self, q: tuple[float, float], f: tuple[float, float] | None, ts: Timestamp, tick: str
    ) -> SceneUpdate:
        x1, y1 = self.l1 * math.cos(q[0]), self.l1 * math.sin(q[0])
        cam = self.camera_pose(q)
        meta = [KeyValuePair(key="tick", value=tick)]

        def link(x0: float, y0: float, angle: float, length: float, width: float) -> CubePrimitive:
            c, s = math.cos(angle), math.sin(angle)
            return CubePrimitive(
                pose=Pose(
                    position=Vector3(x=x0 + c * length / 2, y=y0 + s * length / 2, z=0.0),
                    orientation=_yaw(angle),
                ),
                size=Vector3(x=length, y=width, z=width),
                color=_GREY,
            )

        def ball(x: float, y: float, z: float, d: float, color: Color) -> SpherePrimitive:
            return SpherePrimitive(
                pose=Pose(position=Vector3(x=x, y=y, z=z), orientation=_yaw(0.0)),
                size=Vector3(x=d, y=d, z=d),
                color=color,
            )

        arm = SceneEntity(
            timestamp=ts,
            frame_id=WORLD,
            id="arm",
            metadata=meta,
            cubes=[link(0.0, 0.0, q[0], self.l1, 0.04), link(x1, y1, cam[2], self.l2, 0.03)],
            spheres=[
                ball(0.0, 0.0, 0.0, 0.07, _BLUE),
                ball(x1, y1, 0.0, 0.055, _BLUE),
                ball(cam[0], cam[1], 0.0, 0.04, _ORANGE),
            ],
        )
        entities = [arm, self._frustum(ts, meta)]
        if f is not None:
            tx, ty, tz = self.target(cam, f)
            entities.append(
                SceneEntity(
                    timestamp=ts,
                    frame_id=WORLD,
                    id="target",
                    metadata=meta,
                    spheres=[ball(tx, ty, tz, 0.03, _RED)],
                    lines=[
                        LinePrimitive(
                            type=LinePrimitiveLineType.LineStrip,
                            thickness=0.004,
                            points=[Point3(x=cam[0], y=cam[1], z=0.0), Point3(x=tx, y=ty, z=tz)],
                            color=_RED,
                        )
                    ],
                )
            )
        return SceneUpdate(entities=entities)

    def _frustum(self, ts: Timestamp, meta: list[KeyValuePair]) -> SceneEntity:
        """The camera's field of view down to the target plane, in the ``camera`` frame."""
        z = self.depth
        hx, hy = self.cx / self.focal * z, self.cy / self.focal * z
        corners = [
            Point3(x=sx * hx, y=sy * hy, z=z) for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))
        ]
        apex = Point3(x=0.0, y=0.0, z=0.0)
        points: list[Point3] = []
        for i, c in enumerate(corners):
            points += [apex, c, c, corners[(i + 1) % 4]]
        goal = Point3(x=0.0, y=0.0, z=z)
        return SceneEntity(
            timestamp=ts,
            frame_id=CAMERA,
            id="camera",
            frame_locked=True,
            metadata=meta,
            lines=[
                LinePrimitive(
                    type=LinePrimitiveLineType.LineList,
                    thickness=0.003,
                    points=points,
                    color=_ORANGE,
                ),
                LinePrimitive(  # the optical axis: where f = 0 puts the target
                    type=LinePrimitiveLineType.LineStrip,
                    thickness=0.002,
                    points=[apex, goal],
                    color=_GREEN,
                ),
            ],
        )

    def camera_marker(self, pose: tuple[float, float, float], log_time_ns: int) -> SceneUpdate:
        """The emulator's true camera pose (live only): a small cyan arrow along the hand."""
        x, y, phi = pose
        return SceneUpdate(
            entities=[
                SceneEntity(
                    timestamp=_stamp(log_time_ns),
                    frame_id=WORLD,
                    id="camera_emulator",
                    arrows=[
                        ArrowPrimitive(
                            pose=Pose(position=Vector3(x=x, y=y, z=0.02), orientation=_yaw(phi)),
                            shaft_length=0.06,
                            shaft_diameter=0.01,
                            head_length=0.03,
                            head_diameter=0.025,
                            color=Color(r=0.1, g=0.9, b=0.9, a=1.0),
                        )
                    ],
                )
            ]
        )

    def calibration(self, ts: Timestamp) -> CameraCalibration:
        """The image's pinhole: the paper's (s·lambda, centre, no lens), or on images the
        emulated camera's true intrinsics and lens (the frames' own)."""
        (fx, fy), cx, cy = self.focal_xy, self.cx, self.cy
        return CameraCalibration(
            timestamp=ts,
            frame_id=CAMERA,
            width=self.size[0],
            height=self.size[1],
            distortion_model="plumb_bob",
            D=self.dist,
            K=[fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
            R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            P=[fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
        )

    def annotations(
        self, f: tuple[float, float] | None, ts: Timestamp, tick: str
    ) -> ImageAnnotations:
        cx, cy = self.cx, self.cy
        cross = [
            Point2(x=cx - 12, y=cy),
            Point2(x=cx + 12, y=cy),
            Point2(x=cx, y=cy - 12),
            Point2(x=cx, y=cy + 12),
        ]
        points = [
            PointsAnnotation(
                timestamp=ts,
                type=PointsAnnotationType.LineList,
                points=cross,
                outline_color=_GREEN,
                thickness=2.0,
            )
        ]
        circles, texts = [], []
        if f is not None:
            u, v = cx + f[0], cy + f[1]
            circles.append(
                CircleAnnotation(
                    timestamp=ts,
                    position=Point2(x=u, y=v),
                    diameter=14.0,
                    thickness=3.0,
                    fill_color=_RED,
                    outline_color=_WHITE,
                )
            )
            points.append(
                PointsAnnotation(
                    timestamp=ts,
                    type=PointsAnnotationType.LineStrip,
                    points=[Point2(x=cx, y=cy), Point2(x=u, y=v)],
                    outline_color=_RED,
                    thickness=1.0,
                )
            )
            texts.append(
                TextAnnotation(
                    timestamp=ts,
                    position=Point2(x=u + 10, y=v - 10),
                    text=f"f = ({f[0]:.1f}, {f[1]:.1f}) px",
                    font_size=14.0,
                    text_color=_WHITE,
                    background_color=Color(r=0.0, g=0.0, b=0.0, a=0.6),
                )
            )
        return ImageAnnotations(
            circles=circles,
            points=points,
            texts=texts,
            metadata=[KeyValuePair(key="tick", value=tick)],
        )

    def image(self, ts: Timestamp) -> CompressedImage:
        """A dark image plane for the Image panel to draw the annotations on."""
        return CompressedImage(timestamp=ts, frame_id=CAMERA, data=self._png, format="png")
