"""The vision process (``hil vision``): camera poses in, image features out, over zenoh.

It subscribes to ``hil/emulator/camera_pose``, computes f = project(camera, pose, target(t)) with
the scenario's target motion at the pose's simulation time (the t = 3 s jump included), adds the
configured Gaussian pixel noise (seeded), runs a frame clock and a latency delay line, and
publishes ``hil/vision/features`` (schema: :mod:`hal.vision_codec`).

Two modes, chosen per pose by its lockstep flag (or forced with ``lockstep=True/False``):

* **lockstep** — every pose is answered by exactly one features message with ``pose_seq`` = the
  pose's ``seq``, right away. The frame clock and the latency run in *simulation* time: a frame
  is captured at a pose whose sim time reached the next frame slot (slots at k / fps from sim time
  0; ``fps = 0`` captures at every pose) and becomes deliverable ``latency_s`` of sim time later.
  The answer carries the newest deliverable frame — a frame not yet due re-sends the previous one
  with its old frame counter and capture times — or ``valid = 0`` before the first delivery. The
  controller waits for ``pose_seq >= k``, so a lockstep run is deterministic. A pose the DSP
  sends again (it re-announces a period while it waits for the command) gets the same answer
  again, so an answer lost on its way costs a re-send, not the period's features.
* **realtime** — once the world runs (pose sim time > 0), a frame is captured at the first pose
  whose sim time reached the next slot, slots at k / fps of scenario time as in lockstep, so the
  frames' phase against the control ticks is the same in every run, whenever the controller
  started. While the world holds its initial state (sim time 0), frames come from a
  monotonic-clock frame clock and the newest pose (none while that pose is older than
  ``pose_timeout_s``: the emulator went silent). Frames are published ``latency_s`` of real time
  after capture; ``fps = 0`` captures at every pose.

A frame is stamped with its pose's stamp, the time the arm was in that pose (a camera's
exposure), never later than its arrival here, and its latency counts from there: stamped on
arrival, f looked younger than it was by the emulator's step and the link.

A new emulator run (new pose source id, or lockstep sim time going backwards) restarts the frame
counter, clocks and noise generator, so repeated runs against one vision process are identical.
The generator starts from the seed the poses name (a scenario reset that carried one, see
:meth:`hal.joint_client.JointClient.reset_scenario`), else from ``camera.seed``.

Fault injection: ``--dropout START:DURATION`` (repeatable;
:class:`~plant_emulator.vision_timing.Dropout`) pauses the publisher
for ``[START, START + DURATION)`` seconds of the run's *simulation* time (the pose's sim time; in
realtime the newest pose's sim time advanced by the real time since it arrived). During a dropout
no image is captured and frames whose delivery falls into it are discarded. In realtime nothing is
published; in lockstep every pose is still answered (the protocol needs one answer per period),
with ``valid = 0`` and ``f = (0, 0)``, so the controller's newest valid message ages in sim time
and goes stale exactly as it would on a silent camera.
"""

from __future__ import annotations

import contextlib
import secrets
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import zenoh

from hal.config import RigConfig, plant_view
from hal.errors import HalError
from hal.secoc import AnotherKeyNotice, rig_key
from hal.vision_codec import FeatureMsg, PoseMsg, encode_features, is_resend
from hal.vision_receivers import PoseDecoder
from hal.zenoh_session import (
    DEFAULT_WAIT_S,
    KEY_CAMERA_POSE,
    KEY_FEATURES,
    ZenohSession,
    open_session,
)
from plant_emulator.camera import CameraPose, project
from plant_emulator.scenario import paper_target
from plant_emulator.vision_timing import DEFAULT_FPS, Dropout, FrameClock, in_dropout, resolve_fps

POSE_TIMEOUT_S = 0.5
"""Realtime: no frames are captured from a pose older than this."""


@dataclass
class VisionStats:
    """What the vision process did (printed by ``hil vision --json``)."""

    mode: str = "auto"
    fps: float = DEFAULT_FPS
    poses: int = 0
    """Poses accepted by the pose decoder."""
    frames: int = 0
    """Images captured."""
    published: int = 0
    """Features messages published."""
    answers: int = 0
    """Lockstep answers (one per accepted lockstep pose)."""
    resends: int = 0
    """Lockstep answers re-sending an older frame (the next one was not due yet)."""
    invalid: int = 0
    """Messages published with valid = 0 (no frame delivered yet)."""
    skipped_no_pose: int = 0
    """Realtime frame slots skipped because the newest pose was too old."""
    runs: int = 0
    """Emulator runs seen (a new source id or sim time going backwards starts one)."""
    publish_errors: int = 0
    pose_rx: dict[str, int] = field(default_factory=dict)
    """The pose decoder's counters (malformed/stale poses)."""
    callback_errors: int = 0
    dropouts: list[str] = field(default_factory=list)
    """The configured dropout windows, ``START:DURATION`` (s of simulation time)."""
    dropout_frames: int = 0
    """Frame slots not captured because they fell into a dropout."""
    dropout_discarded: int = 0
    """Captured frames discarded because their delivery fell into a dropout."""
    dropout_answers: int = 0
    """Lockstep answers sent with valid = 0 during a dropout (also counted in ``invalid``)."""
    reanswers: int = 0
    """Lockstep: answers sent again, unchanged, to a pose the DSP sent again (it was waiting
    for the period's command; the first answer may have been lost)."""

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class VisionCore:
    """The vision process's logic without I/O: feed poses and clock ticks, get messages."""

    def __init__(
        self,
        cfg: RigConfig,
        *,
        fps: float,
        lockstep: bool | None = None,
        source: int = 0,
        pose_timeout_s: float = POSE_TIMEOUT_S,
        dropouts: Sequence[Dropout] = (),
    ) -> None:
        cfg = plant_view(cfg)  # the plant's camera and target (model mismatch: [plant])
        self.camera = cfg.camera
        self.dropouts = tuple(dropouts)
        self.target = paper_target(cfg)
        self.fps = fps
        self.lockstep = lockstep
        self.source = source
        self.latency_ns = round(cfg.camera.latency_s * 1e9)
        self.pose_timeout_ns = round(pose_timeout_s * 1e9)
        self.stats = VisionStats(
            mode="auto" if lockstep is None else ("lockstep" if lockstep else "realtime"),
            fps=fps,
            dropouts=[str(d) for d in self.dropouts],
        )
        self._run_key: tuple[int, bool, int | None] | None = None
        self._last_stamp_ns = 0
        self._new_run()

    def _new_run(self, seed: int | None = None) -> None:
        """Start a run: frame counter, clocks, and the noise generator from ``seed`` (the one
        the emulator's scenario reset named), else from ``camera.seed``."""
        self.frame = 0
        self.seed = self.camera.seed if seed is None else seed
        self.rng = np.random.default_rng(self.seed)
        self.sim_clock = FrameClock(self.fps, origin_ns=0)
        self.rt_clock = FrameClock(self.fps)
        self.pending: deque[tuple[int, FeatureMsg]] = deque()
        self.delivered: FeatureMsg | None = None
        self.pose: PoseMsg | None = None
        self.pose_recv_ns = 0
        self.last_sim_ns: int | None = None
        self.answer: FeatureMsg | None = None
        """Lockstep: the answer to :attr:`pose` (sent again when the pose is)."""

    def is_lockstep(self, pose: PoseMsg) -> bool:
        return pose.lockstep if self.lockstep is None else self.lockstep

    def measure(self, pose: PoseMsg) -> tuple[float, float]:
        """Features of the target at the pose's sim time, seen from the pose, plus noise."""
        target = self.target.position(pose.sim_time_ns * 1e-9)
        f = project(self.camera, CameraPose(pose.x, pose.y, pose.phi), target)
        if self.camera.noise_px > 0:
            f = f + self.rng.normal(0.0, self.camera.noise_px, size=2)
        return (float(f[0]), float(f[1]))

    def _exposed_ns(self, pose: PoseMsg, now_ns: int) -> int:
        """When a frame of ``pose`` is exposed: the pose's stamp, when the arm was there (its
        arrival here is later by the emulator's step and the link, and a frame stamped then
        looks younger than it is); never after ``now_ns`` (a clock ahead of this one) nor
        before the previous frame's (the receiver refuses stamps going backwards)."""
        return min(now_ns, max(pose.stamp_ns, self._last_stamp_ns))

    def _capture(self, pose: PoseMsg, stamp_ns: int, t_ns: int, lockstep: bool) -> None:
        """A frame of ``pose`` exposed at ``stamp_ns``, delivered ``latency_s`` after ``t_ns``
        on the delay line's clock."""
        self._last_stamp_ns = max(self._last_stamp_ns, stamp_ns)
        msg = FeatureMsg(
            self.frame,
            stamp_ns,
            pose.sim_time_ns,
            pose.seq,
            self.measure(pose),
            True,
            lockstep,
            self.source,
        )
        self.frame += 1
        self.stats.frames += 1
        self.pending.append((t_ns + self.latency_ns, msg))

    def _paused(self, sim_ns: int) -> bool:
        return bool(self.dropouts) and in_dropout(self.dropouts, sim_ns)

    def _rt_sim_ns(self, now_ns: int) -> int:
        """Realtime: the emulator's sim time now, from the newest pose and its age."""
        pose = self.pose
        return 0 if pose is None else pose.sim_time_ns + max(0, now_ns - self.pose_recv_ns)

    def _deliver(self, t_ns: int, sim_ns: int) -> list[FeatureMsg]:
        """Frames due by ``t_ns`` (the delay line's clock); all discarded when the publisher is
        paused at simulation time ``sim_ns``."""
        out = []
        while self.pending and self.pending[0][0] <= t_ns:
            out.append(self.pending.popleft()[1])
        if out and self._paused(sim_ns):
            self.stats.dropout_discarded += len(out)
            return []
        if out:
            self.delivered = out[-1]
        return out

    def on_pose(self, pose: PoseMsg, now_ns: int) -> list[FeatureMsg]:
        """Take an accepted pose; the messages to publish now (lockstep: exactly one; a
        re-sent pose gets its answer again, unchanged)."""
        lockstep = self.is_lockstep(pose)
        if lockstep and self.answer is not None and is_resend(pose, self.pose):
            self.stats.reanswers += 1
            return [self.answer]
        key = (pose.source, lockstep, pose.seed)
        restart = self._run_key != key or (
            lockstep and self.last_sim_ns is not None and pose.sim_time_ns < self.last_sim_ns
        )
        if restart:
            self._new_run(pose.seed)
            self._run_key = key
            self.stats.runs += 1
        self.stats.poses += 1
        self.pose, self.pose_recv_ns, self.last_sim_ns = pose, now_ns, pose.sim_time_ns
        paused = self._paused(pose.sim_time_ns)
        if not lockstep:
            if self.fps > 0:
                # sim time 0 is the held world: its frames take slot 0 (see poll)
                if self.sim_clock.due(pose.sim_time_ns) and pose.sim_time_ns > 0:
                    if paused:
                        self.stats.dropout_frames += 1
                    else:
                        exposed = self._exposed_ns(pose, now_ns)
                        self._capture(pose, exposed, exposed, False)
                return self._deliver(now_ns, pose.sim_time_ns)
            if paused:
                self.stats.dropout_frames += 1
            else:
                exposed = self._exposed_ns(pose, now_ns)
                self._capture(pose, exposed, exposed, False)
            return self._deliver(now_ns, pose.sim_time_ns)
        t = pose.sim_time_ns
        if self.sim_clock.due(t):
            if paused:
                self.stats.dropout_frames += 1
            else:
                self._capture(pose, self._exposed_ns(pose, now_ns), t, True)
        self._deliver(t, t)
        self.stats.answers += 1
        d = self.delivered
        if paused:
            # One answer per pose even now: not valid, and ordered after the last one sent
            # (same frame counter, newer pose_seq), so the receiver accepts it.
            self.stats.invalid += 1
            self.stats.dropout_answers += 1
            frame = 0 if d is None else d.frame
            return self._answer(
                FeatureMsg(frame, now_ns, t, pose.seq, (0.0, 0.0), False, True, self.source)
            )
        if d is None:
            self.stats.invalid += 1
            return self._answer(
                FeatureMsg(0, now_ns, t, pose.seq, (0.0, 0.0), False, True, self.source)
            )
        if d.pose_seq != pose.seq:
            self.stats.resends += 1
        return self._answer(d._replace(pose_seq=pose.seq))

    def _answer(self, msg: FeatureMsg) -> list[FeatureMsg]:
        self.answer = msg
        return [msg]

    def poll(self, now_ns: int) -> list[FeatureMsg]:
        """Realtime frame clock and delay line at monotonic time ``now_ns``."""
        pose = self.pose
        if pose is None or self.is_lockstep(pose):
            return []
        sim_ns = self._rt_sim_ns(now_ns)
        if self.fps > 0 and pose.sim_time_ns == 0 and self.rt_clock.due(now_ns):
            if now_ns - self.pose_recv_ns > self.pose_timeout_ns:
                self.stats.skipped_no_pose += 1
            elif self._paused(sim_ns):
                self.stats.dropout_frames += 1
            else:
                self._capture(pose, now_ns, now_ns, False)
        return self._deliver(now_ns, sim_ns)

    def next_wakeup_ns(self) -> int | None:
        """When :meth:`poll` has work next (realtime), or None."""
        pose = self.pose
        if pose is None or self.is_lockstep(pose):
            return None
        times = [self.pending[0][0]] if self.pending else []
        nxt = self.rt_clock.next_ns if pose.sim_time_ns == 0 else None
        if nxt is not None:
            times.append(nxt)
        return min(times) if times else None


class VisionNode:
    """:class:`VisionCore` on a zenoh session: poses arrive on zenoh's callback thread (lockstep
    answers are published from there), realtime frames from :meth:`run`'s thread."""

    def __init__(
        self,
        cfg: RigConfig,
        session: ZenohSession,
        *,
        fps: float,
        lockstep: bool | None = None,
        source: int | None = None,
        dropouts: Sequence[Dropout] = (),
    ) -> None:
        self.session = session
        self.core = VisionCore(
            cfg,
            fps=fps,
            lockstep=lockstep,
            source=secrets.randbits(32) if source is None else source,
            dropouts=dropouts,
        )
        self.key = rig_key(cfg)
        self.decoder = PoseDecoder(key=self.key)
        self.bad_mac_notice = AnotherKeyNotice("hil vision", "camera poses")
        """Said at the first pose whose MAC does not verify (counted ``pose_rx.bad_mac``)."""
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._pub = session.publisher(KEY_FEATURES)
        self._sub = session.subscribe(KEY_CAMERA_POSE, self._on_pose)

    @property
    def stats(self) -> VisionStats:
        with self._lock:
            s = self.core.stats
            s.pose_rx = self.decoder.counts.as_dict()
            s.callback_errors = self.session.callback_errors
            return VisionStats(**asdict(s))

    def _publish(self, msgs: list[FeatureMsg]) -> None:
        for msg in msgs:
            try:
                self._pub.put(encode_features(msg, self.key))
                self.core.stats.published += 1
            except (zenoh.ZError, HalError):
                self.core.stats.publish_errors += 1

    def _on_pose(self, payload: bytes) -> None:
        now = time.monotonic_ns()
        pose = self.decoder.feed(payload, now)
        if pose is None:
            if self.decoder.counts.bad_mac:
                self.bad_mac_notice.say()
            return
        with self._lock:
            self._publish(self.core.on_pose(pose, now))
            idle = self.core.next_wakeup_ns() is None
        if idle and not self.core.is_lockstep(pose):
            self._wake.set()  # start the realtime frame clock now, not at the next idle tick

    def step(self, now_ns: int | None = None) -> int | None:
        """Run the realtime clock once; returns the next wake-up time (monotonic ns) or None."""
        with self._lock:
            self._publish(self.core.poll(time.monotonic_ns() if now_ns is None else now_ns))
            return self.core.next_wakeup_ns()

    def run(self, stop_event: threading.Event, duration_s: float = 0.0) -> VisionStats:
        """Serve until ``stop_event`` is set or ``duration_s`` (0 = forever) elapsed."""
        end = time.monotonic_ns() + round(duration_s * 1e9) if duration_s > 0 else None
        while not stop_event.is_set():
            self._wake.clear()  # before step(): a pose arriving from here on wakes the wait
            nxt = self.step()
            now = time.monotonic_ns()
            if end is not None and now >= end:
                break
            wait_ns = 50_000_000 if nxt is None else max(0, nxt - now)
            if end is not None:
                wait_ns = min(wait_ns, end - now)
            self._wake.wait(min(wait_ns, 50_000_000) / 1e9)
        return self.stats

    def close(self) -> None:
        """Undeclare the subscriber and publishers (the session stays open). Idempotent."""
        for entity in (self._sub, self._pub):
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()


def run_vision(
    cfg: RigConfig,
    *,
    fps: float | None = None,
    lockstep: bool | None = None,
    stop_event: threading.Event | None = None,
    duration_s: float = 0.0,
    endpoint: str | None = None,
    config_file: str | None = None,
    listen: bool | None = False,
    wait_s: float = DEFAULT_WAIT_S,
    session: ZenohSession | None = None,
    ready: threading.Event | None = None,
    dropouts: Sequence[Dropout] = (),
) -> VisionStats:
    """Run the vision process until ``stop_event`` or ``duration_s`` (0 = forever).

    ``fps`` as :func:`resolve_fps`; ``lockstep=None`` follows each pose's flag. The zenoh options
    go to :func:`hal.zenoh_session.open_session` (by default a client of the emulator's hub,
    ``listen=True`` to be the hub); a given ``session`` is used as is and left open. ``ready``
    is set once poses are subscribed. ``dropouts``: publisher pauses (fault injection).
    """
    stop_event = stop_event or threading.Event()
    fps = resolve_fps(cfg, fps)
    own = session is None
    if session is None:
        session = open_session(
            cfg,
            listen=listen,
            endpoint=endpoint,
            config_file=config_file,
            wait_s=wait_s,
            stop_event=stop_event,
        )
    try:
        node = VisionNode(cfg, session, fps=fps, lockstep=lockstep, dropouts=dropouts)
        try:
            if ready is not None:
                ready.set()
            return node.run(stop_event, duration_s)
        finally:
            node.close()
    finally:
        if own:
            session.close()
