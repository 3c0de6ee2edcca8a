"""Issue 15: the live view. ``hil up --lockstep --monitor`` with independent Foxglove WebSocket
clients (:mod:`tests.support.foxglove_ws`, written from the protocol, not from foxglove-sdk).

* a reading client subscribes to the cycle and scene topics; the cycles arrive in tick order and
  are byte-for-byte the run's MCAP messages; the scene messages decode with the advertised
  protobuf schema and equal the MCAP's scene of the same tick (time stamps aside);
* a second client subscribes to everything and never reads: the controller's run stays clean
  (exit 0, the full tick count, nothing lost).

No wall-clock assertion: the run's length is counted in ticks.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from mcap.reader import make_reader

from hal.zenoh_session import free_loopback_port
from rt_controller.monitor.camera_view import IMAGE_TOPIC
from rt_controller.monitor.scene import SCENE_TOPIC, TF_TOPIC
from rt_controller.runtime.recorder import CYCLE_TOPIC
from tests.support.foxglove_ws import FoxgloveClient, decoder_for
from vision.sources import decode_compressed_image

pytestmark = [pytest.mark.integration, pytest.mark.slow]

DURATION_S = 30.0
TICKS = 1500  # 30 s at 50 Hz


def _mcap_messages(path: Path) -> dict[str, list[tuple[int, bytes]]]:
    out: dict[str, list[tuple[int, bytes]]] = {}
    with open(path, "rb") as fh:
        for _schema, channel, message in make_reader(fh).iter_messages(log_time_order=False):
            out.setdefault(channel.topic, []).append((message.log_time, message.data))
    return out


def _without_stamps(scene):
    for entity in scene.entities:
        entity.ClearField("timestamp")
    return scene


def test_monitor_streams_the_run_and_a_silent_client_changes_nothing(tmp_path: Path):
    port = free_loopback_port()
    log = tmp_path / "run.mcap"
    up = subprocess.Popen(
        [
            sys.executable, "-m", "rt_controller.cli", "up", "--lockstep", "--json",
            "--duration", f"{DURATION_S:g}", "--monitor", "--monitor-port", str(port),
            "--log", str(log),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )  # fmt: skip
    url = f"ws://127.0.0.1:{port}"
    received: list = []
    errors: list[BaseException] = []
    clients: list[FoxgloveClient] = []
    try:
        reader = FoxgloveClient.open(url)
        clients.append(reader)
        silent = FoxgloveClient.open(url, max_queue=1, max_size=2**24)
        clients.append(silent)
        topics = {CYCLE_TOPIC, SCENE_TOPIC, TF_TOPIC, IMAGE_TOPIC}
        reader.wait_channels(topics)
        silent.wait_channels(topics)
        silent.subscribe(sorted(silent.channels))  # everything, then never read again
        reader.subscribe(sorted(topics))
        advertised = dict(reader.channels)  # the server unadvertises them when it stops

        def read() -> None:
            try:
                while True:
                    msg = reader.recv(timeout=120)
                    if msg is not None:
                        received.append(msg)
            except Exception as exc:  # the server closes the connection when the rig stops
                if "ConnectionClosed" not in type(exc).__name__:
                    errors.append(exc)

        thread = threading.Thread(target=read, daemon=True)
        thread.start()
        out, err = up.communicate(timeout=240)
        thread.join(30)
    finally:
        if up.poll() is None:
            up.kill()
            up.communicate()
        for client in clients:
            client.ws.close_socket()
            client.ws.close()
    assert up.returncode == 0, err.decode()[-2000:]
    summary = json.loads(out.decode().strip().splitlines()[-1])
    assert summary["ticks"] == TICKS
    assert summary["problems"] == []
    assert summary["exit_codes"]["monitor"] == 0
    assert not errors, errors
    channels = advertised
    assert channels[CYCLE_TOPIC]["encoding"] == "json"
    assert channels[CYCLE_TOPIC]["schemaName"] == "hil.ControllerCycle"
    assert channels[CYCLE_TOPIC]["schemaEncoding"] == "jsonschema"
    assert json.loads(channels[CYCLE_TOPIC]["schema"])["title"] == "hil.ControllerCycle"
    assert channels[SCENE_TOPIC]["schemaName"] == "foxglove.SceneUpdate"
    assert channels[TF_TOPIC]["schemaName"] == "foxglove.FrameTransforms"

    logged = _mcap_messages(log)
    mcap_cycles = {json.loads(d)["tick"]: d for _t, d in logged[CYCLE_TOPIC]}
    assert len(mcap_cycles) == TICKS

    live_cycles = [m.payload for m in received if m.topic == CYCLE_TOPIC]
    assert live_cycles, "no cycle arrived live"
    ticks = [json.loads(p)["tick"] for p in live_cycles]
    assert ticks == sorted(ticks) and len(set(ticks)) == len(ticks)
    for tick, payload in zip(ticks, live_cycles, strict=True):
        assert payload == mcap_cycles[tick]  # the same bytes as the log

    # what the camera saw (camera.model = "image", the default), live: the frames, 640x480
    live_images = [m.payload for m in received if m.topic == IMAGE_TOPIC]
    assert live_images, "no camera image arrived live"
    assert channels[IMAGE_TOPIC]["schemaName"] == "foxglove.CompressedImage"
    assert decode_compressed_image(live_images[-1]).shape == (480, 640)

    SceneUpdate = decoder_for(channels[SCENE_TOPIC])
    FrameTransforms = decoder_for(channels[TF_TOPIC])

    def tick_of(scene) -> int:
        meta = {kv.key: kv.value for kv in scene.entities[0].metadata}
        return int(meta["tick"])

    mcap_scenes = {}
    for _t, data in logged[SCENE_TOPIC]:
        scene = SceneUpdate.FromString(data)
        mcap_scenes[tick_of(scene)] = _without_stamps(scene)
    assert len(mcap_scenes) == TICKS  # 50 Hz: every tick is drawn into the log
    live_scenes = [SceneUpdate.FromString(m.payload) for m in received if m.topic == SCENE_TOPIC]
    assert live_scenes, "no scene arrived live"
    scene_ticks = [tick_of(s) for s in live_scenes]
    assert scene_ticks == sorted(scene_ticks)
    for tick, scene in zip(scene_ticks, live_scenes, strict=True):
        assert {e.id for e in scene.entities} >= {"arm", "camera", "target"}
        assert _without_stamps(scene) == mcap_scenes[tick]
    tfs = [FrameTransforms.FromString(m.payload) for m in received if m.topic == TF_TOPIC]
    assert tfs and [t.child_frame_id for t in tfs[-1].transforms] == ["link1", "link2", "camera"]
