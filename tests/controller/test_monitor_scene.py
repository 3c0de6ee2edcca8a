"""Issue 15 (unit level): the scene drawn from a cycle record, the recorder's live sink and scene
channels, the layout's scene panels, and ``hil monitor``'s refusal of a non-loopback host."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader

from hal.config import RigConfig
from rt_controller.cli import main
from rt_controller.monitor.bridge import EMULATOR_SCENE_TOPIC
from rt_controller.monitor.camera_view import DETECTION_TOPIC
from rt_controller.monitor.scene import (
    ANNOTATIONS_TOPIC,
    CALIBRATION_TOPIC,
    IMAGE_TOPIC,
    SCENE_TOPIC,
    TF_TOPIC,
    SceneBuilder,
)
from rt_controller.runtime.recorder import CYCLE_TOPIC, DIAGNOSTICS_TOPIC, CycleRecorder

ROOT = Path(__file__).resolve().parents[2]


def _cycle(tick: int) -> dict:
    q = [math.pi / 6 + 0.01 * tick, -math.pi / 6]
    return {"tick": tick, "t_ns": 1_000_000 + tick * 20_000_000, "q": q, "dq": [0.0, 0.0],
            "f": [-120.0 + tick, -160.0]}  # fmt: skip


def _decoders(path: Path) -> tuple[dict[str, list[bytes]], dict[str, object]]:
    msgs: dict[str, list[bytes]] = {}
    classes: dict[str, object] = {}
    with open(path, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages():
            msgs.setdefault(channel.topic, []).append(message.data)
            if schema.encoding == "protobuf" and channel.topic not in classes:
                pool = descriptor_pool.DescriptorPool()
                for fd in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
                    pool.Add(fd)
                desc = pool.FindMessageTypeByName(schema.name)
                classes[channel.topic] = message_factory.GetMessageClass(desc)
    return msgs, classes


def test_the_target_drawn_is_what_the_camera_sees():
    cfg = RigConfig()
    b = SceneBuilder(cfg)
    q = (0.4, -0.9)
    x, y, phi = b.camera_pose(q)
    assert x == pytest.approx(0.26 * math.cos(0.4) + 0.26 * math.cos(-0.5))
    assert phi == pytest.approx(-0.5)
    f = (-120.0, -160.0)
    tx, ty, tz = b.target((x, y, phi), f)
    assert tz == cfg.camera.z_wo
    c, s = math.cos(phi), math.sin(phi)  # eq. (6) forwards gives f back
    g = cfg.camera.gain
    assert g * (c * (tx - x) + s * (ty - y)) == pytest.approx(f[0])
    assert g * (-s * (tx - x) + c * (ty - y)) == pytest.approx(f[1])


def test_no_finite_q_draws_nothing():
    b = SceneBuilder(RigConfig())
    assert b.messages({"tick": 1, "q": [None, 0.0], "f": [1.0, 2.0]}, 0) == []


def test_recorder_sends_the_logged_bytes_live_and_draws_the_scene(tmp_path: Path):
    cfg = RigConfig()
    sent: list[tuple[str, bytes]] = []
    path = tmp_path / "run.mcap"
    with CycleRecorder(path, cfg, scene=SceneBuilder(cfg), live=None) as rec:
        rec.live = lambda topic, data: sent.append((topic, data))
        for k in range(60):
            rec.record_cycle(_cycle(k))
        rec.record_diagnostics({"t_ns": 5, "tick": 60, "status": []}, final=True)
    msgs, classes = _decoders(path)
    assert [d for t, d in sent if t == CYCLE_TOPIC] == msgs[CYCLE_TOPIC]
    assert [d for t, d in sent if t == DIAGNOSTICS_TOPIC] == msgs[DIAGNOSTICS_TOPIC]
    for topic in (TF_TOPIC, SCENE_TOPIC, CALIBRATION_TOPIC, ANNOTATIONS_TOPIC):
        assert len(msgs[topic]) == 60, topic  # 50 Hz: every tick drawn
    # camera.model = "image" (the default): /camera/image holds the camera's own frames
    # (rt_controller/monitor/camera_view.py); the blank plane is only the analytic camera's,
    # with ticks 0 and 50: about 1 Hz
    assert not msgs.get(IMAGE_TOPIC)
    analytic = SceneBuilder(cfg.with_overrides({"camera.model": "analytic"}))
    drawn = [[t for t, _ in analytic.messages(_cycle(k), 0)] for k in range(60)]
    assert sum(topics.count(IMAGE_TOPIC) for topics in drawn) == 2
    scene = classes[SCENE_TOPIC].FromString(msgs[SCENE_TOPIC][7])
    assert {e.id for e in scene.entities} == {"arm", "camera", "target"}
    arm = next(e for e in scene.entities if e.id == "arm")
    assert {kv.key: kv.value for kv in arm.metadata} == {"tick": "7"}
    tip = arm.spheres[2].pose.position
    x, y, _ = SceneBuilder(cfg).camera_pose(_cycle(7)["q"])
    assert (tip.x, tip.y) == pytest.approx((x, y))
    tf = classes[TF_TOPIC].FromString(msgs[TF_TOPIC][0])
    assert [(t.parent_frame_id, t.child_frame_id) for t in tf.transforms] == [
        ("world", "link1"), ("link1", "link2"), ("link2", "camera"),
    ]  # fmt: skip
    ann = classes[ANNOTATIONS_TOPIC].FromString(msgs[ANNOTATIONS_TOPIC][3])
    # about the principal point of the camera's frames, ((w - 1) / 2, (h - 1) / 2) on images
    cx, cy = cfg.camera.true_principal_point_px
    assert ann.circles[0].position.x == pytest.approx(cx - 117.0)
    assert ann.circles[0].position.y == pytest.approx(cy - 160.0)
    assert rec.scene_written == 4 * 60 and rec.live_sent == 61  # no blank plane on images
    assert rec.as_dict()["written"] == 61  # the counters of the cycle log are unchanged


def test_a_failing_live_sink_never_costs_the_log(tmp_path: Path):
    def broken(_topic: str, _data: bytes) -> None:
        raise RuntimeError("monitor gone")

    path = tmp_path / "run.mcap"
    with CycleRecorder(path, RigConfig(), live=broken) as rec:
        for k in range(20):
            rec.record_cycle(_cycle(k))
    assert rec.live_errors == 20 and rec.finished
    assert rec.as_dict()["/controller/cycle"] == 20 and rec.as_dict()["dropped"] == 0


def test_layout_scene_panels_use_the_topics_we_publish():
    layout = json.loads((ROOT / "foxglove" / "layout.json").read_text(encoding="utf-8"))
    panels = layout["configById"]
    published = set(SceneBuilder.schemas()) | {EMULATOR_SCENE_TOPIC}
    assert set(panels["3D!arm"]["topics"]) <= published
    image = panels["Image!camera"]["imageMode"]
    assert image["imageTopic"] == IMAGE_TOPIC
    assert image["calibrationTopic"] == CALIBRATION_TOPIC
    assert set(image["annotations"]) == {ANNOTATIONS_TOPIC, DETECTION_TOPIC}


def test_monitor_refuses_a_remote_host_unless_told(capsys):
    assert main(["monitor", "--host", "0.0.0.0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--allow-remote" in err
