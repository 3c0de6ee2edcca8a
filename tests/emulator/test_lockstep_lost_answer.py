"""A lockstep answer lost between the vision process and the controller (zenoh drops a sample
published before the controller's subscription reached the hub: a plan's next run, a busy
host) is recovered by the DSP's re-sent pose, with the very same features. Seen before: the
controller waited its 1 s out, ran tick 0 without features and the run's J changed
(``hil experiment fig3 --noise 0.5``: ioc J 17.5672 instead of 17.5638)."""

from __future__ import annotations

import numpy as np

from hal.config import RigConfig
from hal.secoc import rig_key
from hal.vision_codec import FeatureMsg, PoseMsg, encode_features, encode_pose
from hal.vision_receivers import FeatureDecoder, PoseDecoder
from plant_emulator.camera import camera_pose
from plant_emulator.vision_node import VisionCore

MS = 1_000_000
PERIOD = 20 * MS


class Chain:
    """DSP poses → the vision process (its decoder and core) → the controller's decoder, each
    message encoded and authenticated as on the wire."""

    def __init__(self, cfg: RigConfig) -> None:
        self.cfg, self.key = cfg, rig_key(cfg)
        self.poses = PoseDecoder(key=self.key)
        self.core = VisionCore(cfg, fps=0.0, source=9)
        self.features = FeatureDecoder.from_config(cfg.controller, key=self.key)
        p = camera_pose(cfg.robot, np.array(cfg.scenario.q0))
        self.xyphi = (p.x, p.y, p.phi)

    def pose(self, seq: int, stamp_ns: int) -> list[FeatureMsg]:
        """The DSP publishes pose ``seq``; the answers the vision process publishes."""
        msg = PoseMsg(seq, seq * PERIOD, stamp_ns, *self.xyphi, True, 77, 5)
        got = self.poses.feed(encode_pose(msg, self.key), stamp_ns)
        return [] if got is None else self.core.on_pose(got, stamp_ns)

    def deliver(self, answers: list[FeatureMsg], now_ns: int) -> None:
        for a in answers:
            self.features.feed(encode_features(a, self.key), now_ns)


def test_a_lost_answer_comes_again_unchanged_when_the_dsp_resends_the_pose() -> None:
    cfg = RigConfig().with_overrides({"camera.noise_px": 0.5})
    lossy, clean = Chain(cfg), Chain(cfg)

    first = lossy.pose(0, 1 * MS)  # published, lost on its way: the controller sees nothing
    assert len(first) == 1 and lossy.features.wait_pose_seq(0, 0.0) is None
    again = lossy.pose(0, 41 * MS)  # the DSP waited sync_resend_s and sent pose 0 again
    assert again == first
    lossy.deliver(again, 42 * MS)
    assert lossy.features.wait_pose_seq(0, 0.0) == first[0]

    clean.deliver(clean.pose(0, 1 * MS), 2 * MS)
    for seq in range(1, 6):  # no extra noise was drawn: the runs go on identically
        now = (seq + 1) * 50 * MS
        lossy.deliver(lossy.pose(seq, now), now)
        clean.deliver(clean.pose(seq, now), now)
        assert lossy.features.last == clean.features.last
    assert lossy.core.stats.reanswers == 1 and lossy.core.stats.answers == 6
    assert lossy.poses.counts.resent == 1 and lossy.poses.counts.rejected == 0


def test_an_answer_that_arrives_twice_is_a_resend_not_a_rejection() -> None:
    """When the first answer was only late, the controller gets it twice: the second is
    counted ``resent``, changes nothing and is no rejection (diagnostics stay OK)."""
    chain = Chain(RigConfig())
    answer = chain.pose(0, 1 * MS)
    chain.deliver(answer, 2 * MS)
    chain.deliver(chain.pose(0, 41 * MS), 42 * MS)
    c = chain.features.counts
    assert c.accepted == 1 and c.resent == 1 and c.rejected == 0
    assert chain.features.last == answer[0]
    chain.deliver(chain.pose(1, 60 * MS), 61 * MS)  # the next period is news again
    assert chain.features.pose_seq == 1 and c.accepted == 2 and c.rejected == 0
