"""The emulated network camera: renders frames from the arm's pose and streams them on zenoh.

It runs inside ``hil emulator`` (``camera.model = "image"``), next to the arm, as a network
camera is bolted to a real one: the DSP node hands it every camera pose it publishes
(:meth:`CameraNode.offer`, no zenoh round trip), a worker thread renders
(:class:`plant_emulator.camera_sensor.CameraSensor`) and publishes each frame on
``hil/camera/frame`` (:mod:`hal.camera_frame`) for the vision process's frame grabber.

* **lockstep** — exactly one frame per control period: the pose of period k ends the exposure
  (the frame is stamped at its middle, ``t_k - exposure / 2``; the arm's motion over the
  exposure is interpolated from the poses of periods k - 1 and k) and the frame carries
  ``period = k``. A re-sent pose (the DSP re-announces a period while it waits) gets the same
  frame again, byte for byte. Noise is keyed by (seed, frame), so a run is bit-exact for a seed.
  Once a frame is sent, the next frame's background and noise are made while the pose of its
  period is awaited (:meth:`CameraSensor.prepare`; the pixels are a whole render's).
* **realtime** — the camera's own frame clock: frame j is exposed around ``j / fps`` of scenario
  time and rendered once a pose at or after the end of its exposure has arrived (poses come at
  ``rates.state_hz``; the motion is interpolated between them). Slots the renderer could not
  keep up with are skipped and counted, never bunched. While the world holds its initial state
  (sim time 0) frames come on a monotonic clock at the same rate from the newest pose.

* **region of interest** — the frame grabber names the region of the next frame it will read
  (:class:`hal.camera_frame.RoiRequest` on ``hil/camera/roi``, :meth:`CameraNode.request`) and
  the camera renders, authenticates and sends only it (:meth:`CameraSensor.render_window`: the
  whole frame's pixels there), with its offset in the header. Whole frames: when no region was
  asked for (the grabber has no tracking window), for the first frame of each image-log slot
  (``camera.image_log_fps``, the image log's own rule on the same simulation times,
  :class:`hal.vision_image.ImageSlots`: the log and the live views show whole frames), and a
  frame sent as a region again whole when the grabber asks (its target was not in the
  region). In lockstep, once the grabber asks, the camera waits for the request of each frame
  (sent right after the features that lead to the next pose, it is normally there first;
  :data:`ROI_WAIT_S` at most, then the whole frame, counted ``roi_late``), so which frames are
  regions is the same on every run. A request that is malformed, unauthentic or for another
  camera is counted and dropped; a window outside the frame is clamped to it.

A new emulator run (a scenario reset: new pose source id; or sim time going backwards) restarts
the frame counter and the noise with the seed the reset named (else ``camera.seed``), under a
new frame source id (the grabber takes the restarted counter as a new camera).

Why a thread of the emulator and not a process of its own: the camera needs the pose at the
emulator's own rate and nothing else, ``hil up`` starts it with the arm, and the renderer spends
its time in numba, numpy and hashing, mostly without the GIL, so it does not make the DSP loop
late (docs/benchmarks.md, "Design choices, measured").
"""

from __future__ import annotations

import secrets
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass

from hal.camera_frame import RoiRequest, decode_roi_request, encode_frame
from hal.config import RigConfig
from hal.errors import HalError
from hal.fifo import fifo_thread, short_gil_switch
from hal.vision_image import ImageSlots
from plant_emulator.camera import CameraPose
from plant_emulator.camera_poses import PoseHistory, PoseSample
from plant_emulator.camera_rig import sensor_from_config
from plant_emulator.camera_sensor import CameraSensor

DEFAULT_FPS = 60.0
"""Realtime frame rate when ``camera.frame_rate_hz`` is 0 (the XC-HR57's)."""
HISTORY_S = 0.25
"""Realtime: how much pose history the renderer keeps for a frame's exposure."""
ROI_WAIT_S = 0.05
"""Lockstep: how long the camera waits for the grabber's region request of a frame."""
ROI_KEEP = 8
"""Region requests kept (by frame), newest first."""


@dataclass(frozen=True)
class _WholeAgain:
    """The grabber asks frame ``seq`` (sent as a region) again whole."""

    seq: int


@dataclass
class CameraStats:
    """What the camera did (in ``hil emulator --json``)."""

    frames: int = 0
    """Frames rendered and published."""
    resent: int = 0
    """Lockstep: frames re-published for a re-sent pose."""
    skipped: int = 0
    """Realtime: frame slots skipped because the renderer fell behind."""
    unwatched: int = 0
    """Realtime: frame slots not rendered because no frame grabber listened."""
    runs: int = 0
    publish_errors: int = 0
    render_errors: int = 0
    """Batches of poses whose frames could not be made (an unexpected error; the first is
    printed on stderr)."""
    render_ms_max: float = 0.0
    render_ms_sum: float = 0.0
    roi_frames: int = 0
    """Frames sent as a region of interest."""
    whole_again: int = 0
    """Frames sent as a region and then again whole, asked for by the grabber."""
    roi_requests: int = 0
    """Region requests accepted."""
    roi_rejected: int = 0
    """Region requests malformed or not authentic (dropped)."""
    roi_other: int = 0
    """Region requests for another camera or run, or a frame no longer at hand (dropped)."""
    roi_clamped: int = 0
    """Requested windows reaching outside the frame (clamped to it; none inside: whole)."""
    roi_late: int = 0
    """Lockstep frames sent whole because their request did not come in time."""

    def as_dict(self) -> dict[str, float]:
        d = asdict(self)
        d["render_ms_mean"] = self.render_ms_sum / self.frames if self.frames else 0.0
        del d["render_ms_sum"]
        return d


class CameraNode:
    """Renders and publishes frames for the poses it is offered (see the module docstring).

    ``publish`` sends one encoded frame (raises on a broken link: counted, never fatal);
    ``watched`` says whether a frame grabber listens: realtime frames nobody would receive are
    not rendered (counted ``unwatched``; lockstep always renders, its frames are the run's)."""

    def __init__(
        self,
        cfg: RigConfig,
        publish: Callable[[bytes], object],
        *,
        key: bytes | None = None,
        fps: float | None = None,
        sensor: CameraSensor | None = None,
        clock: Callable[[], int] = time.monotonic_ns,
        watched: Callable[[], bool] | None = None,
    ) -> None:
        self.cfg = cfg
        self.sensor = sensor or sensor_from_config(cfg)
        self.publish = publish
        self.key = key
        fps = cfg.camera.frame_rate_hz if fps is None else fps
        self.fps = fps if fps > 0 else DEFAULT_FPS
        self.period_ns = round(1e9 / self.fps)
        self.exposure_ns = round(self.sensor.exposure_s * 1e9)
        self.stats = CameraStats()
        self.source = secrets.randbits(32)
        self._clock = clock
        self._watched = watched
        self._cond = threading.Condition()
        self._queue: deque[tuple[PoseSample, bool] | tuple[None, int | _WholeAgain | None]] = (
            deque()
        )
        """Offered poses (and lockstep flags) in order, scenario resets (None, seed) and frames
        asked again whole (None, _WholeAgain)."""
        self._history = PoseHistory(round(HISTORY_S * 1e9))
        self._thread: threading.Thread | None = None
        self._lockstep = False
        """Whether the newest pose was a lockstep one (then no realtime frame clock runs)."""
        self._stop = threading.Event()
        self._fifo_asked = False
        self._requests: dict[int, RoiRequest] = {}
        """Region requests of this run's frames, by frame (under ``_cond``)."""
        self._asked = False
        """Whether the grabber asks for regions (this run): lockstep then waits for them."""
        self._log_slots = ImageSlots(cfg.camera.image_log_fps)
        """The image log's frames (its own rule, :class:`hal.vision_image.ImageSlots`): whole."""
        self._new_run(None)

    # -- feeding (the DSP's thread) --------------------------------------------------------

    def offer(
        self,
        seq: int,
        sim_time_ns: int,
        pose: CameraPose,
        lockstep: bool,
        stamp_ns: int | None = None,
    ) -> None:
        """A camera pose the emulator publishes (the pose sink's signature); returns at once.
        ``stamp_ns``: when the arm was in the pose (a SYNC-stepped world's SYNC), else now."""
        sample = PoseSample(seq, sim_time_ns, self._clock() if stamp_ns is None else stamp_ns, pose)
        with self._cond:
            self._queue.append((sample, lockstep))
            self._cond.notify()

    def new_run(self, seed: int | None) -> None:
        """A scenario reset: restart the frame counter and the noise (``seed``, else
        ``camera.seed``) before the next pose."""
        with self._cond:
            self._queue.append((None, seed))
            self._cond.notify()

    def request(self, payload: bytes) -> None:
        """A region request from the frame grabber (zenoh's callback thread); never raises."""
        try:
            req = decode_roi_request(payload, self.key)
        except HalError:
            self.stats.roi_rejected += 1
            return
        with self._cond:
            if req.source != self.source:
                self.stats.roi_other += 1
                return
            self.stats.roi_requests += 1
            if req.seq < self._frame:  # a frame already made: asked again whole?
                if req.window is None:
                    self._queue.append((None, _WholeAgain(req.seq)))
                else:
                    self.stats.roi_other += 1
            else:
                self._requests[req.seq] = req
                for old in sorted(self._requests)[:-ROI_KEEP]:
                    del self._requests[old]
                self._asked = True
            self._cond.notify_all()

    # -- the worker ------------------------------------------------------------------------

    def start(self) -> CameraNode:
        """Compile and warm the renderer (the first frame would otherwise be late by the JIT
        time), then start the worker thread."""
        self.sensor.warm_up()
        self.sensor.render(lambda t: CameraPose(0.0, 0.0, 0.0), 0.0)
        short_gil_switch()  # the renderer's Python holds the GIL the DSP thread wants
        self._thread = threading.Thread(target=self._run, name="hil-camera", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop the worker (frames not yet rendered are dropped). Idempotent."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._cond:
                if not self._queue:
                    self._cond.wait(timeout=self._idle_wait_s())
            try:
                self.drain()
                if not self._fifo_asked and not self._lockstep and self._history.newest:
                    self._realtime_thread()
            except Exception as exc:  # a frame lost, never the camera (or the arm beside it)
                self.stats.render_errors += 1
                if self.stats.render_errors == 1:
                    print(
                        f"hil emulator: camera: frame lost: {type(exc).__name__}: {exc} "
                        "(further errors only counted)",
                        file=sys.stderr,
                        flush=True,
                    )

    def drain(self) -> None:
        """Handle every pose offered so far, then any realtime frame now due (the worker's
        body; tests call it directly instead of :meth:`start`)."""
        with self._cond:
            batch = list(self._queue)
            self._queue.clear()
        self._step(batch)

    def _idle_wait_s(self) -> float:
        """Realtime, world holding: wake for the next monotonic frame slot."""
        if self._hold_next_ns is None:
            return 0.1
        return min(0.1, max(0.0, (self._hold_next_ns - self._clock()) * 1e-9))

    def _new_run(self, seed: int | None) -> None:
        # a new source id, as a restarted camera: the frame grabber's decoder orders frames by
        # (seq, period) per source, and the counter restarts here
        self.source = secrets.randbits(32)
        self._seed = self.cfg.camera.seed if seed is None else seed
        self.sensor.seed = self._seed
        self._frame = 0
        self._history.clear()
        self._last_lockstep: tuple[int, bytes] | None = None
        self._next_slot = 0
        self._hold_next_ns: int | None = None
        with self._cond:
            self._requests.clear()
            self._asked = False
        self._log_slots.reset()
        self._last_mid: float | None = None
        self._made: tuple[int, float, int, bool, int] | None = None
        """The newest frame sent as a region: (frame, t_mid, period, lockstep, stamp_ns)."""
        self.stats.runs += 1

    def _step(
        self, batch: list[tuple[PoseSample, bool] | tuple[None, int | _WholeAgain | None]]
    ) -> None:
        for sample, flag in batch:
            if isinstance(flag, _WholeAgain):
                self._whole_again(flag.seq)
                continue
            if sample is None:
                self._new_run(flag)
                continue
            self._lockstep = lockstep = bool(flag)
            newest = self._history.newest
            if newest is not None and sample.sim_ns < newest.sim_ns:
                self._new_run(self._seed)  # time went backwards: a new run
            if lockstep:
                self._answer(sample)
            else:
                self._history.add(sample)
        if not self._lockstep:
            self._realtime_frames()

    def _answer(self, sample: PoseSample) -> None:
        last = self._last_lockstep
        if last is not None and last[0] == sample.seq:
            self._send(last[1])
            self.stats.resent += 1
            return
        self._history.add(sample)
        t_end = sample.sim_ns * 1e-9
        t_mid = t_end - self.sensor.exposure_s / 2
        payload = self._render(t_mid, sample.seq, True, sample.stamp_ns - self.exposure_ns // 2)
        self._last_lockstep = (sample.seq, payload)
        self._send(payload)
        step = t_mid - self._last_mid if self._last_mid is not None else 0.0
        self._last_mid = t_mid
        self._prepare_next(t_mid, t_mid + step)

    def _realtime_frames(self) -> None:
        newest = self._history.newest
        if newest is None:
            return
        if newest.sim_ns == 0:  # the world holds: a monotonic frame clock, the newest pose
            now = self._clock()
            if self._hold_next_ns is None:
                self._hold_next_ns = now
            if now >= self._hold_next_ns:
                self._hold_next_ns += self.period_ns * max(
                    1, (now - self._hold_next_ns) // self.period_ns + 1
                )
                if self._watching():
                    self._send(self._render(0.0, newest.seq, False, now - self.exposure_ns // 2))
            return
        self._hold_next_ns = None
        half = self.exposure_ns // 2
        due = (newest.sim_ns - half) // self.period_ns  # the newest slot whose exposure ended
        if due < self._next_slot:
            return
        if due > self._next_slot:
            self.stats.skipped += due - self._next_slot
        self._next_slot = due + 1
        if self._watching():
            t_mid = due * self.period_ns * 1e-9
            stamp = self._history.stamp_at(t_mid)
            self._send(self._render(t_mid, newest.seq, False, stamp))
            self._prepare_next(t_mid, t_mid + self.period_ns * 1e-9)

    def _watching(self) -> bool:
        if self._watched is None or self._watched():
            return True
        self.stats.unwatched += 1
        return False

    def _render(self, t_mid: float, period: int, lockstep: bool, stamp_ns: int) -> bytes:
        """The next frame, whole or the region the grabber asked for."""
        window = self._window(round(t_mid * 1e9), lockstep)
        payload = self._encode(self._frame, t_mid, period, lockstep, stamp_ns, window)
        self._made = (self._frame, t_mid, period, lockstep, stamp_ns) if window else None
        self._frame += 1
        return payload

    def _window(self, sim_ns: int, lockstep: bool) -> tuple[int, int, int, int] | None:
        """The region to send of the next frame (None: whole); see the module docstring."""
        first_of_slot = self._log_slots.take(sim_ns)
        with self._cond:
            n = self._frame
            waiting = lockstep and self._asked and n not in self._requests
            if waiting and not self._cond.wait_for(
                lambda: n in self._requests or self._stop.is_set(), ROI_WAIT_S
            ):
                self.stats.roi_late += 1
            req = self._requests.pop(n, None)
            if req is None and not lockstep:  # realtime: the grabber may be a frame behind
                older = [k for k in self._requests if n - 2 <= k < n]
                req = self._requests[max(older)] if older else None
        if req is None or first_of_slot:
            return None
        h, w = self.sensor.shape
        window = req.clamped(w, h)
        if window is not None and window != req.window:
            self.stats.roi_clamped += 1
        return window

    def _whole_again(self, seq: int) -> None:
        """The grabber asks frame ``seq``, sent as a region, again whole."""
        made = self._made
        if made is None or made[0] != seq:
            self.stats.roi_other += 1
            return
        self._made = None
        frame, t_mid, period, lockstep, stamp_ns = made
        payload = self._encode(frame, t_mid, period, lockstep, stamp_ns, None)
        self.stats.whole_again += 1
        if lockstep and self._last_lockstep is not None and self._last_lockstep[0] == period:
            self._last_lockstep = (period, payload)  # a re-sent pose gets the whole frame
        self._send(payload)

    def _encode(
        self,
        frame: int,
        t_mid: float,
        period: int,
        lockstep: bool,
        stamp_ns: int,
        window: tuple[int, int, int, int] | None,
    ) -> bytes:
        t0 = time.perf_counter()
        if window is None:
            pixels = self.sensor.render(self._history.pose_at, t_mid, frame=frame)
            x0 = y0 = 0
        else:
            pixels = self.sensor.render_window(self._history.pose_at, t_mid, window, frame=frame)
            x0, y0 = window[0], window[1]
            self.stats.roi_frames += 1
        h, w = self.sensor.shape
        payload = encode_frame(
            pixels,
            seq=frame,
            stamp_ns=stamp_ns,
            sim_time_ns=round(t_mid * 1e9),
            exposure_ns=self.exposure_ns,
            period=period,
            lockstep=lockstep,
            source=self.source,
            key=self.key,
            x0=x0,
            y0=y0,
            sensor_size=(w, h),
        )
        ms = (time.perf_counter() - t0) * 1e3
        self.stats.frames += 1
        self.stats.render_ms_sum += ms
        self.stats.render_ms_max = max(self.stats.render_ms_max, ms)
        return payload

    def _realtime_thread(self) -> None:
        """Realtime: the camera is hardware beside the DSP, never starved by the host's other
        processes: its thread on SCHED_FIFO one priority below the DSP loop's
        (``dsp.rt_priority``; 0 leaves it alone, as for the DSP). Measured (realtime rig at
        60 fps, 8 s of ioc, load 14): 30-41 frame slots skipped with normal scheduling, none
        with SCHED_FIFO. A refusal is one warning."""
        self._fifo_asked = True
        why = fifo_thread(max(self.cfg.dsp.rt_priority - 1, 0))
        if why:
            print(
                f"hil emulator: warning: camera: {why}; it runs with normal scheduling",
                file=sys.stderr,
                flush=True,
            )

    def _prepare_next(self, t: float, t_next: float) -> None:
        """While the next pose is awaited: the next frame's background and noise, which no
        pose changes (lockstep: the controller and the DSP work meanwhile; the pose of the
        next period is not known before its torque is), so only the target's region is
        rendered once the pose is there (:meth:`CameraSensor.prepare`; same pixels). Not while
        the grabber asks for regions, unless the next frame starts an image-log slot (sent
        whole; ``t_next``: its mid-exposure, about)."""
        if self._asked and not self._log_slots.due(round(t_next * 1e9)):
            return
        self.sensor.prepare(self._frame, self.sensor.scene(t).background)

    def _send(self, payload: bytes) -> None:
        try:
            self.publish(payload)
        except HalError:  # a broken link is counted, never fatal to the arm
            self.stats.publish_errors += 1
