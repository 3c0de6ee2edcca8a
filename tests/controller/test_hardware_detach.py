"""The hardware profile's feature subscription ends at ``deactivate``: zenoh may still run a
subscriber's callback after the undeclare returns (its thread had the sample already), and the
run's log is closed right after the deactivation. A message delivered then must reach neither the
decoder nor the log; in a plan that shares its processes it showed up as "1 log record(s)
lost" on a clean lockstep run."""

from __future__ import annotations

import threading
from typing import Any

import can

from hal.bus import isolated_spec
from hal.config import RigConfig
from hal.joint_client import JointClient
from hal.secoc import rig_key
from hal.vision_codec import FeatureMsg, encode_features
from hal.vision_receivers import FeatureDecoder
from hal.zenoh_session import KEY_FEATURES
from rt_controller.runtime.context import RunContext
from rt_controller.runtime.counters import RunCounters
from rt_controller.runtime.feature_link import FeatureLink
from rt_controller.runtime.hardware import DspHardware
from tests.support.fake_clock import FakeClock


class LateSession:
    """A session whose subscriber keeps the callback after its undeclare, as zenoh's callback
    thread does with a sample it already took."""

    def __init__(self) -> None:
        self.callback: Any = None
        self.undeclared = False

    def subscribe(self, key: str, on_payload: Any) -> Any:
        if key == KEY_FEATURES:  # not the image stream's subscription (hil/vision/image)
            self.callback = on_payload
        session = self

        class Subscriber:
            def undeclare(self) -> None:
                session.undeclared = True

        return Subscriber()


class ListRecorder:
    dropped = 0

    def __init__(self) -> None:
        self.vision: list[bytes] = []

    def record_vision(self, payload: bytes, t_ns: int) -> bool:
        self.vision.append(payload)
        return True


def _payload(cfg: RigConfig, seq: int, stamp_ns: int) -> bytes:
    msg = FeatureMsg(seq, stamp_ns, 0, seq, (-120.0, -160.0), True, True, 7)
    return encode_features(msg, key=rig_key(cfg))


def test_a_feature_message_delivered_after_deactivate_reaches_neither_decoder_nor_log() -> None:
    cfg = RigConfig()
    clock = FakeClock(1_000_000_000)
    decoder = FeatureDecoder.from_config(cfg.controller, key=rig_key(cfg))
    rec = ListRecorder()
    session = LateSession()
    stopped = threading.Event()
    stopped.set()  # configure subscribes, then returns at once (no DSP answers here)
    ctx = RunContext(cfg, clock, stopped, RunCounters(), rec)
    with JointClient.open(isolated_spec("virtual"), cfg) as dsp:
        link = FeatureLink(ctx, session, decoder, by_callback=True, record_raw=True)
        hw = DspHardware(ctx, dsp, link, lockstep=True, record_raw=True)
        hw.configure(stopped)
        session.callback(_payload(cfg, 1, clock.now_ns()))
        assert len(rec.vision) == 1 and decoder.latest is not None
        first = decoder.latest

        hw.deactivate()
        assert session.undeclared
        # zenoh's thread, after the undeclare returned:
        session.callback(_payload(cfg, 2, clock.now_ns()))

    assert len(rec.vision) == 1
    assert decoder.latest == first


class FailingCanRecorder(ListRecorder):
    """A recorder whose raw-frame call raises, as a bug in the log path would."""

    def record_can(self, msg: Any, t_ns: int, direction: str) -> bool:
        raise RuntimeError("the log path broke")


def test_raw_frames_the_log_hook_could_not_record_count_as_lost_log_records() -> None:
    """A raw-frame hook that raises never stops the frame (:class:`hal.can_tap.FrameTap`), and
    the frame it could not log is a lost log record in the run's summary, so such a run is not
    clean (it was counted only on the tap, where no summary looks)."""
    cfg = RigConfig()
    clock = FakeClock(1_000_000_000)
    decoder = FeatureDecoder.from_config(cfg.controller, key=rig_key(cfg))
    rec = FailingCanRecorder()
    stopped = threading.Event()
    stopped.set()
    ctx = RunContext(cfg, clock, stopped, RunCounters(), rec)
    with JointClient.open(isolated_spec("virtual"), cfg) as dsp:
        link = FeatureLink(ctx, LateSession(), decoder, by_callback=True, record_raw=False)
        hw = DspHardware(ctx, dsp, link, lockstep=True, record_raw=True)
        hw.configure(stopped)
        for _ in range(3):
            dsp.bus.send(can.Message(arbitration_id=0x7FF, data=b"\x01", is_extended_id=False))
        hw.deactivate()
        dsp.bus.send(can.Message(arbitration_id=0x7FF, data=b"\x02", is_extended_id=False))
    assert rec.dropped == 3  # the frame after the deactivation is not this run's
