"""``hil monitor``: the rig's zenoh streams bridged to a Foxglove WebSocket server (foxglove-sdk).

Channels advertised (the names and JSON Schemas of the MCAP, so ``foxglove/layout.json`` works
live as it does for a log):

============================== ============================ ======================================
topic                          schema                       from
============================== ============================ ======================================
``/controller/cycle``          ``hil.ControllerCycle`` json ``hil/controller/cycle`` (as sent)
``/diagnostics``               ``hil.Diagnostics`` json     ``hil/controller/diagnostics``
``/tf`` ``/scene/arm``         ``foxglove.*`` protobuf      drawn from each cycle record
``/camera/*``                                               (:mod:`rt_controller.monitor.scene`)
``/vision/features/decoded``   ``hil.Features`` json        ``hil/vision/features``
``/emulator/camera_pose``      ``hil.CameraPose`` json      ``hil/emulator/camera_pose``
``/scene/emulator``            ``foxglove.SceneUpdate``     the emulator's true camera pose
============================== ============================ ======================================

Never in the rig's way: zenoh delivers into bounded rings (zenoh's ``RingChannel``: no Python
callback on zenoh's threads, the oldest sample goes when a ring is full) drained by one worker
thread; the server drops the oldest messages of a client that does not read
(``message_backlog_size``). The camera-pose subscription starts only after the first cycle record
arrives, so a monitor never counts as the vision process the lockstep emulator waits for.

With a :class:`~rt_controller.monitor.access.TlsIdentity` the server accepts ``wss://`` only
(foxglove-sdk's ``tls_cert``/``tls_key``); who may change the rig is the tuning front-end's gate.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from foxglove.messages import SceneUpdate

import foxglove
from foxglove import Channel, Schema
from hal.config import RigConfig
from hal.errors import HalCodecError
from hal.log_topics import (
    CAMERA_POSE_TOPIC,
    CYCLE_TOPIC,
    DIAGNOSTICS_TOPIC,
    EMULATOR_SCENE_TOPIC,
    FEATURES_DECODED_TOPIC,
)
from hal.secoc import rig_key
from hal.vision_codec import decode_features, decode_pose
from hal.vision_image import decode_vision_image
from hal.zenoh_session import (
    KEY_CAMERA_POSE,
    KEY_CONTROLLER_CYCLE,
    KEY_CONTROLLER_DIAGNOSTICS,
    KEY_FEATURES,
    KEY_VISION_IMAGE,
    PayloadRing,
    ZenohSession,
)
from rt_controller.errors import ControllerError
from rt_controller.monitor.access import TlsIdentity
from rt_controller.monitor.camera_view import SCHEMAS as CAMERA_VIEW_SCHEMAS
from rt_controller.monitor.camera_view import view_messages
from rt_controller.monitor.scene import SceneBuilder
from rt_controller.monitor.tuning import TuningFrontEnd
from rt_controller.runtime.diagnostics import DIAGNOSTICS_SCHEMA
from rt_controller.runtime.recorder import cycle_schema, encode_json

log = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765
RING_CAPACITY = 4096
"""Samples a zenoh ring keeps for the worker (lockstep runs reach thousands of cycles/s)."""
SIDE_MAX_HZ = 50.0
"""Features and camera poses are forwarded at most this often (the emulator sends up to 1 kHz)."""
BACKLOG = 1024
"""Messages the server queues per client before it drops the oldest."""

FEATURES_SCHEMA: dict[str, Any] = {
    "title": "hil.Features",
    "description": "A features message of hil/vision/features, decoded (hal.vision_codec).",
    "type": "object",
    "properties": {
        "frame": {"type": "integer"},
        "stamp_ns": {"type": "integer"},
        "sim_time_ns": {"type": "integer"},
        "pose_seq": {"type": "integer"},
        "f": {"type": "array", "items": {"type": "number"}, "description": "features, px"},
        "valid": {"type": "boolean"},
        "lockstep": {"type": "boolean"},
        "source": {"type": "integer"},
    },
}
POSE_SCHEMA: dict[str, Any] = {
    "title": "hil.CameraPose",
    "description": "The emulator's camera pose (hil/emulator/camera_pose): position in the arm's "
    "plane (m) and heading q1 + q2 (rad).",
    "type": "object",
    "properties": {
        "seq": {"type": "integer"},
        "sim_time_ns": {"type": "integer"},
        "stamp_ns": {"type": "integer"},
        "x": {"type": "number"},
        "y": {"type": "number"},
        "phi": {"type": "number"},
        "lockstep": {"type": "boolean"},
        "source": {"type": "integer"},
    },
}


PORT_HINT = "; choose another with --port PORT (hil up: --monitor-port PORT; 0 = any)"
"""Appended to a refusal of a port in use (another monitor, e.g. a second rig's, serves it)."""


class MonitorError(ControllerError, OSError):
    """The monitor cannot serve (address in use, bad host)."""


def _json_channel(topic: str, schema: dict[str, Any]) -> Channel:
    return Channel(
        topic,
        schema=Schema(name=schema["title"], encoding="jsonschema", data=encode_json(schema)),
        message_encoding="json",
    )


def _proto_channel(topic: str, cls: Any) -> Channel:
    s = cls.get_schema()
    return Channel(
        topic,
        schema=Schema(name=s.name, encoding=s.encoding, data=bytes(s.data)),
        message_encoding="protobuf",
    )


class MonitorBridge:
    """The Foxglove server and its channels, fed from a zenoh session by one worker thread.

    ``start()`` subscribes and starts the worker; ``close()`` (idempotent) stops both and the
    server. :attr:`counts` says what went through.
    """

    poll_s = 0.005

    def __init__(
        self,
        cfg: RigConfig,
        session: ZenohSession,
        *,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        clock: Callable[[], int] = time.time_ns,
        tuning: TuningFrontEnd | None = None,
        tls: TlsIdentity | None = None,
    ) -> None:
        self.cfg = cfg
        self.session = session
        self.clock = clock
        self.builder = SceneBuilder(cfg)
        self.counts = {
            "cycles": 0,
            "diagnostics": 0,
            "scenes": 0,
            "features": 0,
            "poses": 0,
            "images": 0,
            "bad": 0,
            "images_refused": 0,
        }
        self._side_period_ns = round(1e9 / SIDE_MAX_HZ)
        self._last_side: dict[str, int] = {}
        self._channels: dict[str, Channel] = {
            CYCLE_TOPIC: _json_channel(CYCLE_TOPIC, cycle_schema()),
            DIAGNOSTICS_TOPIC: _json_channel(DIAGNOSTICS_TOPIC, DIAGNOSTICS_SCHEMA),
            FEATURES_DECODED_TOPIC: _json_channel(FEATURES_DECODED_TOPIC, FEATURES_SCHEMA),
            CAMERA_POSE_TOPIC: _json_channel(CAMERA_POSE_TOPIC, POSE_SCHEMA),
        }
        for topic, cls in self.builder.schemas().items():
            self._channels[topic] = _proto_channel(topic, cls)
        self._channels[EMULATOR_SCENE_TOPIC] = _proto_channel(EMULATOR_SCENE_TOPIC, SceneUpdate)
        for topic, cls in CAMERA_VIEW_SCHEMAS.items():  # what the camera saw (on images)
            self._channels.setdefault(topic, _proto_channel(topic, cls))
        self.tuning = tuning
        """The calibration front-end (Parameters and Services), None: a view only."""
        extra: dict[str, Any] = {}
        if tuning is not None:
            extra = {
                "capabilities": list(tuning.capabilities),
                "server_listener": tuning,
                "services": tuning.services(),
                "supported_encodings": ["json"],
            }
        if tls is not None:
            extra.update(tls_cert=tls.cert, tls_key=tls.key)
        self.tls = tls is not None
        try:
            self.server = foxglove.start_server(
                name="hil monitor", host=host, port=port, message_backlog_size=BACKLOG, **extra
            )
        except Exception as exc:  # the SDK's own error types (port in use, bad address)
            for ch in self._channels.values():
                ch.close()
            # another monitor (a second rig's) serves the port: say how to choose another
            hint = PORT_HINT if "in use" in str(exc) else ""
            raise MonitorError(
                f"cannot serve Foxglove WebSocket on {host}:{port}: {exc}{hint}"
            ) from exc
        if tuning is not None:
            tuning.server = self.server
        self.port = int(self.server.port)
        self.host = host
        self._rings: dict[str, PayloadRing] = {}
        self.last_record_s: float | None = None
        """``time.monotonic()`` when the last cycle or diagnostics record came (None: none
        yet): how long the rig has been silent (``hil monitor`` says when it stopped)."""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="hil-monitor", daemon=True)
        self._closed = False
        self._server_stopped = threading.Event()

    @property
    def url(self) -> str:
        """What a client opens; an IPv6 address in brackets (``ws://[::1]:8765``)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{'wss' if self.tls else 'ws'}://{host}:{self.port}"

    def channels(self) -> dict[str, str]:
        """Advertised topic -> schema name."""
        return {t: c.schema_name() or "" for t, c in self._channels.items()}

    def start(self) -> MonitorBridge:
        for key in (KEY_CONTROLLER_CYCLE, KEY_CONTROLLER_DIAGNOSTICS, KEY_FEATURES):
            self._rings[key] = self.session.subscribe_ring(key, RING_CAPACITY)
        self._rings[KEY_VISION_IMAGE] = self.session.subscribe_ring(KEY_VISION_IMAGE, 4)
        self._thread.start()
        return self

    # --- worker ---------------------------------------------------------------------------------
    def _run(self) -> None:
        handlers = {
            KEY_CONTROLLER_CYCLE: self._on_cycle,
            KEY_CONTROLLER_DIAGNOSTICS: self._on_diagnostics,
            KEY_FEATURES: self._on_features,
            KEY_CAMERA_POSE: self._on_pose,
            KEY_VISION_IMAGE: self._on_image,
        }
        while not self._stop.is_set():
            busy = False
            for key, ring in list(self._rings.items()):
                for payload in ring.drain():
                    busy = True
                    try:
                        handlers[key](payload)
                    except Exception as exc:  # one bad message never stops the bridge
                        self.counts["bad"] += 1
                        if self.counts["bad"] == 1:
                            log.warning("hil monitor: cannot forward a %s sample: %s", key, exc)
            if not busy:
                self._stop.wait(self.poll_s)

    def _on_cycle(self, payload: bytes) -> None:
        self.last_record_s = time.monotonic()
        now = self.clock()
        self._channels[CYCLE_TOPIC].log(payload, log_time=now)
        self.counts["cycles"] += 1
        if KEY_CAMERA_POSE not in self._rings:  # the rig is running: vision is subscribed
            self._rings[KEY_CAMERA_POSE] = self.session.subscribe_ring(KEY_CAMERA_POSE, 64)
        record = json.loads(payload)
        if self.tuning is not None and isinstance(record.get("param_set"), int):
            self.tuning.param_set_seen(record["param_set"])
        tick = record.get("tick")
        if not isinstance(tick, int) or tick % self.builder.every:
            return
        for topic, msg in self.builder.messages(record, now):
            self._channels[topic].log(msg.encode(), log_time=now)
        self.counts["scenes"] += 1

    def _on_diagnostics(self, payload: bytes) -> None:
        self.last_record_s = time.monotonic()
        self._channels[DIAGNOSTICS_TOPIC].log(payload, log_time=self.clock())
        self.counts["diagnostics"] += 1

    def _due(self, topic: str, now: int) -> bool:
        if now - self._last_side.get(topic, -self._side_period_ns) < self._side_period_ns:
            return False
        self._last_side[topic] = now
        return True

    def _on_features(self, payload: bytes) -> None:
        now = self.clock()
        if not self._due(FEATURES_DECODED_TOPIC, now):
            return
        try:
            msg = decode_features(payload)
        except HalCodecError:
            self.counts["bad"] += 1
            return
        self._channels[FEATURES_DECODED_TOPIC].log(encode_json(msg.as_dict()), log_time=now)
        self.counts["features"] += 1

    def _on_pose(self, payload: bytes) -> None:
        now = self.clock()
        if not self._due(CAMERA_POSE_TOPIC, now):
            return
        try:
            pose = decode_pose(payload)
        except HalCodecError:
            self.counts["bad"] += 1
            return
        self._channels[CAMERA_POSE_TOPIC].log(encode_json(pose._asdict()), log_time=now)
        scene = self.builder.camera_marker((pose.x, pose.y, pose.phi), now)
        self._channels[EMULATOR_SCENE_TOPIC].log(scene.encode(), log_time=now)
        self.counts["poses"] += 1

    def _on_image(self, payload: bytes) -> None:
        """What the camera saw (``hil/vision/image``, authenticated): frame and detection."""
        now = self.clock()
        try:
            img = decode_vision_image(payload, rig_key(self.cfg))
        except HalCodecError as exc:
            self.counts["bad"] += 1
            self.counts["images_refused"] += 1
            if self.counts["images_refused"] == 1:  # most often a monitor given another key
                log.warning(
                    "hil monitor: camera images refused (%s): they are shown only with the "
                    "rig's key (--key-file: the key hil up was given)",
                    exc,
                )
            return
        for topic, msg in view_messages(img, now):
            self._channels[topic].log(msg.encode(), log_time=now)
        self.counts["images"] += 1

    # --- closing --------------------------------------------------------------------------------
    def close(self, timeout_s: float = 2.0) -> bool:
        """Stop the worker, the subscriptions and the server. Idempotent. False when the server
        did not stop within ``timeout_s`` (it waits for its clients' close handshakes, and a
        client that never reads never answers): the caller should then exit the process
        without the SDK's exit hook (``os._exit``)."""
        if self._closed:
            return self._server_stopped.is_set()
        self._closed = True
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5.0)
        for ring in self._rings.values():
            ring.close()
        self._rings.clear()
        for ch in self._channels.values():
            ch.close()

        def stop_server() -> None:
            self.server.stop()
            self._server_stopped.set()

        threading.Thread(target=stop_server, name="hil-monitor-stop", daemon=True).start()
        return self._server_stopped.wait(timeout_s)

    def __enter__(self) -> MonitorBridge:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
