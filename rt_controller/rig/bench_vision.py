"""``hil bench vision``: what the image pipeline costs and how well it measures.

The emulated camera comes in as two callables from the command (``rt_controller`` never
imports the emulator; ``commands/vision.py`` builds them): ``render(cfg, q, dq, frame)`` gives
the frame the camera of ``cfg`` takes at joint angles ``q`` moving at ``dq`` (exposure centred
on ``q``), ``truth(cfg, q)`` the true eq. (6) features there.

Figures (times in us, errors in px, median and p99 where a distribution):

* ``sizes.WxH``: render and detection (decode-free pipeline: detect, refine, undistort,
  convert) time per frame over a grid of poses, default noise; ``detect_cpu_us`` is the
  detection's own CPU time (the wall time also holds what other processes took on a busy host);
  ``detect_tracked_us`` the wall time when the target is found in the tracking window (a
  steady target; ``detect_us`` searches the whole frame);
* ``accuracy.no_noise`` / ``accuracy.default_noise``: RMS and max error against eq. (6) over
  the grid, still arm, 640x480 (no noise also means no exposure blur);
* ``blur``: at the paper's peak arm speed with the default exposure, the fraction of the grid's
  in-view frames the pipeline measured no f in, and the error of the rest (against eq. 6 at
  mid-exposure);
* ``latency``: capture stamp to the features message published, through a loopback zenoh hub,
  frames at ``fps`` in realtime (zenoh transport of the raw frame included);
* ``lockstep``: lockstep rig runs (:data:`LOCKSTEP_RUNS`) with images, with images of a clean
  camera, with images but no image log, and with the analytic camera: speed against real time
  (``speedup_loop``: the ticks' own wall time), the period's profile and J; the clean camera's
  also ``J_vs_analytic``, its J's relative difference from the analytic camera's.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from hal.config import RigConfig
from rt_controller.sample_stats import summary_stats
from vision.intrinsics import intrinsics_from_config
from vision.pipeline import Pipeline

Render = Callable[[RigConfig, np.ndarray, np.ndarray, int], np.ndarray]
Truth = Callable[[RigConfig, np.ndarray], tuple[float, float]]

PEAK_DQ = (1.2, 8.3)
"""The paper scenario's peak joint speeds in live runs, rad/s (``dsp.dq_max``'s docstring)."""
SIZES = ((640, 480), (1280, 1024))
NO_NOISE = {"camera.electrons_per_dn": 0.0, "camera.read_noise_dn": 0.0, "camera.exposure_s": 0.0}
"""A still sensor: no shot or read noise, no exposure (so no motion blur)."""
CLEAN_CAMERA = {
    **NO_NOISE,
    **{f"camera.lens_{c}": 0.0 for c in ("k1", "k2", "p1", "p2", "k3")},
}
"""A still sensor behind an ideal lens: the images whose f is eq. (6)'s to the detector's
sub-pixel error, so a lockstep run on them has the analytic camera's J."""


def pose_grid(cfg: RigConfig, n: int) -> list[np.ndarray]:
    """``n`` x ``n`` joint angles about q(0) (f sweeps most of a 640x480 image)."""
    q0 = np.array(cfg.scenario.q0)
    d1s, d2s = np.linspace(-0.1, 0.1, n), np.linspace(-0.2, 0.15, n)
    return [q0 + np.array((d1, d2)) for d1 in d1s for d2 in d2s]


def _us(ns: list[int]) -> dict[str, float]:
    stats = summary_stats(np.array(ns, dtype=float) / 1e3, ("median", "p99"))
    return {k: round(v, 1) for k, v in stats.items()}


def _in_view(cfg: RigConfig, f: tuple[float, float], margin_px: float = 25.0) -> bool:
    k = intrinsics_from_config(cfg)
    u, v = k.cx + f[0], k.cy + f[1]
    return margin_px <= u <= k.width - margin_px and margin_px <= v <= k.height - margin_px


def timing(cfg: RigConfig, render: Render, poses: list[np.ndarray]) -> dict[str, Any]:
    """Render and detection per frame; ``detect_us``: the whole frame searched (each pose of
    the grid is a jump), ``detect_tracked_us``: the same frames found in the tracking window
    (the pipeline seeded by the frame once, as a steady target in a run)."""
    intrinsics = intrinsics_from_config(cfg)
    pipeline = Pipeline(intrinsics, track=False)
    render_ns, detect_ns, detect_cpu_ns, tracked_ns = [], [], [], []
    still = np.zeros(2)
    pipeline.process(render(cfg, poses[0], still, 0))  # warm up: the sensor's rays, caches
    for i, q in enumerate(poses):
        t0 = time.perf_counter_ns()
        img = render(cfg, q, still, i)
        t1 = time.perf_counter_ns()
        c1 = time.thread_time_ns()
        pipeline.process(img)
        detect_cpu_ns.append(time.thread_time_ns() - c1)
        detect_ns.append(time.perf_counter_ns() - t1)
        render_ns.append(t1 - t0)
        tracker = Pipeline(intrinsics)
        tracker.process(img)
        t2 = time.perf_counter_ns()
        tracker.process(img)
        tracked_ns.append(time.perf_counter_ns() - t2)
    return {
        "render_us": _us(render_ns),
        "detect_us": _us(detect_ns),
        "detect_cpu_us": _us(detect_cpu_ns),
        "detect_tracked_us": _us(tracked_ns),
        "frames": len(poses),
    }


def accuracy(
    cfg: RigConfig, render: Render, truth: Truth, poses: list[np.ndarray], dq: np.ndarray
) -> dict[str, Any]:
    pipeline = Pipeline(intrinsics_from_config(cfg))
    errors, lost, in_view = [], 0, 0
    for i, q in enumerate(poses):
        f_true = truth(cfg, q)
        if not _in_view(cfg, f_true):
            continue
        in_view += 1
        m = pipeline.process(render(cfg, q, dq, i))
        if m.f is None:
            lost += 1
        else:
            errors.append(np.subtract(m.f, f_true))
    e = np.array(errors) if errors else np.zeros((0, 2))
    return {
        "frames": in_view,
        "lost": lost,
        "lost_fraction": round(lost / in_view, 4) if in_view else None,
        "rms_px": round(float(np.sqrt(np.mean(np.square(e)))), 4) if len(e) else None,
        "max_px": round(float(np.abs(e).max()), 4) if len(e) else None,
        "rejected": pipeline.counts.as_dict()["rejected"],
    }


def latency(cfg: RigConfig, render: Render, frames: int, fps: float) -> dict[str, Any]:
    """Frames published in realtime on a loopback hub; the grabber's capture-to-publish times."""
    from hal.camera_frame import encode_frame
    from hal.secoc import rig_key
    from hal.zenoh_session import KEY_CAMERA_FRAME, free_loopback_port, open_session
    from vision.process import run_live

    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    stop, ready, out = threading.Event(), threading.Event(), {}

    def serve() -> None:
        out["stats"] = run_live(
            cfg, "emulated", stop_event=stop, endpoint=endpoint, listen=True, ready=ready
        )

    th = threading.Thread(target=serve, name="bench-vision")
    th.start()
    try:
        if not ready.wait(20):
            return {"error": "the vision process did not start"}
        img = render(cfg, np.array(cfg.scenario.q0), np.zeros(2), 0)
        key = rig_key(cfg)
        with open_session(cfg, listen=False, endpoint=endpoint) as s:
            pub = s.publisher(KEY_CAMERA_FRAME)
            time.sleep(0.3)  # let the subscription reach the hub
            period = 1.0 / fps
            t_next = time.monotonic()
            for i in range(frames):
                now = time.monotonic_ns()
                pub.put(
                    encode_frame(
                        img,
                        seq=i,
                        stamp_ns=now,
                        sim_time_ns=now,
                        exposure_ns=4_000_000,
                        period=i,
                        key=key,
                    )
                )
                t_next += period
                time.sleep(max(0.0, t_next - time.monotonic()))
            time.sleep(0.2)
            pub.undeclare()
    finally:
        stop.set()
        th.join(20)
    stats = out.get("stats")
    if stats is None:
        return {"error": "the vision process ended without its counters"}
    return {
        "fps": fps,
        "frames_sent": frames,
        "frames_measured": stats.valid,
        "capture_to_publish_us": _pair(stats.as_dict(), "latency"),
        "pipeline_us": _pair(stats.as_dict(), "detect"),
        "note": "the frame's stamp is taken when it is sent (render time excluded)",
    }


def _json_line(text: str) -> dict[str, Any]:
    """The last JSON object line a child printed ({} when none)."""
    import json

    for line in reversed(text.splitlines()):
        if line.startswith("{"):
            try:
                return json.loads(line)
            except json.JSONDecodeError:
                continue
    return {}


def rig_run(
    cfg: RigConfig, *, lockstep: bool, duration_s: float, law: str, work: Path
) -> dict[str, Any]:
    """One rig as ``hil up`` starts it (emulator, vision, controller; realtime or lockstep)
    with the vision process's and the emulator's counters: ``{"controller", "vision",
    "emulator", "cycles"}`` (the log's cycle records)."""
    from rt_controller.config_rules import config_toml
    from rt_controller.logtools.reader import read_log
    from rt_controller.rig.options import RigOptions
    from rt_controller.rig.processes import Rig

    conf = work / "rig.toml"
    conf.write_text(config_toml(cfg))
    log = work / "run.mcap"
    opts = RigOptions(
        config=str(conf),
        law=law,
        duration_s=duration_s,
        lockstep=lockstep,
        log=log,
        extra_vision=["--json"],
    )
    with Rig(opts) as rig:
        rig.start()
        summary = rig.wait_controller()
        codes = rig.stop()
        vision_child = rig.child("vision")
        vision = _json_line(vision_child.output())  # type: ignore[union-attr]
        emulator = _json_line(rig.child("emulator").output())  # type: ignore[union-attr]
        vision_tail = "" if vision else vision_child.tail(5)  # type: ignore[union-attr]
    return {
        "vision_tail": vision_tail,
        "controller": summary,
        "vision": vision,
        "emulator": emulator,
        "cycles": read_log(log).cycles,
        "exit_codes": codes,
    }


def _pair(stats: dict[str, Any], name: str) -> dict[str, float | None]:
    p50, p99 = stats.get(f"{name}_us_p50"), stats.get(f"{name}_us_p99")
    return {
        "median": None if p50 is None else round(p50, 1),
        "p99": None if p99 is None else round(p99, 1),
    }


def lockstep_profile(cfg: RigConfig, duration_s: float, law: str = "ioc") -> dict[str, Any]:
    """A lockstep rig with images, and where one period goes (us, median / p99): the
    controller's period and its wait for the features (Sync received to features in), the
    camera's render and encode (emulator), the pose offered to the frame at the grabber
    (render, encode, zenoh), the grabber's frame in to features out (decode, MAC, detect,
    undistort, publish), the DSP and CAN part (torque out to the next Sync)."""
    import tempfile

    from rt_controller.rig.bench_loop import lockstep_period_profile

    with tempfile.TemporaryDirectory(prefix="hil-bench-vision-profile-") as work:
        run = rig_run(
            cfg.with_overrides({"camera.model": "image"}),
            lockstep=True,
            duration_s=duration_s,
            law=law,
            work=Path(work),
        )
    c, v = run["cycles"], run["vision"]
    t = c["t_ns"]
    loop_s = (t[-1] - t[0]) / 1e9 if t.size > 1 else float("nan")
    cam = run["emulator"].get("camera") or {}
    return {
        "sim_s": duration_s,
        "ticks": run["controller"].get("ticks"),
        "J": run["controller"].get("J"),
        "speedup_loop": duration_s / loop_s if loop_s > 0 else None,
        "period_us": lockstep_period_profile(c),
        "camera_render_encode_us_mean": round(1e3 * cam.get("render_ms_mean", float("nan")), 1),
        "pose_to_frame_us": _pair(v, "arrival"),
        "frame_to_features_us": _pair(v, "pipeline"),
        "detect_us": _pair(v, "detect"),
        "image_log": v.get("image_log"),
        "roi": _roi_counters(cam, v),
        "vision_tail": run["vision_tail"],
    }


_CAMERA_ROI_COUNTERS = (
    "frames",
    "roi_frames",
    "whole_again",
    "roi_late",
    "roi_requests",
    "roi_rejected",
    "roi_other",
    "roi_clamped",
)
"""The emulated camera's region-of-interest counters (``hil emulator --json``'s camera)."""


def _roi_counters(camera: dict[str, Any], vision: dict[str, Any]) -> dict[str, Any]:
    """Region-of-interest readout in a rig: the camera's counters and the grabber's (regions
    measured, regions asked for again whole, failed requests)."""
    return {
        "camera": {k: camera.get(k) for k in _CAMERA_ROI_COUNTERS},
        "grabber": {k: vision.get(k) for k in ("roi_frames", "roi_misses", "roi_request_errors")},
    }


def realtime_pipeline(
    cfg: RigConfig, duration_s: float, fps: float = 60.0, law: str = "ioc"
) -> dict[str, Any]:
    """The pipeline's time per frame while a realtime rig with images runs (the processes of
    ``hil up``, the camera at ``fps``): frame in to features out at the grabber (decode, MAC,
    detect, undistort, publish) and the detection alone, median / p99 (us); frames the camera
    rendered, skipped (it fell behind) and the grabber measured, the region-of-interest
    counters; the controller's deadline misses."""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="hil-bench-vision-realtime-") as work:
        run = rig_run(
            cfg.with_overrides({"camera.model": "image", "camera.frame_rate_hz": fps}),
            lockstep=False,
            duration_s=duration_s,
            law=law,
            work=Path(work),
        )
    ctl, v = run["controller"], run["vision"]
    cam = run["emulator"].get("camera") or {}
    rx = v.get("frame_rx") or {}
    rendered = cam.get("frames")
    return {
        "fps": fps,
        "duration_s": duration_s,
        "pipeline_us": _pair(v, "pipeline"),
        "detect_us": _pair(v, "detect"),
        "capture_to_publish_us": _pair(v, "latency"),
        "frames_rendered": rendered,
        "frames_skipped_by_camera": cam.get("skipped"),
        "frames_measured": v.get("frames"),
        "frames_lost_in_transit": (
            rendered - rx.get("accepted", 0) if rendered is not None and rx else None
        ),
        "frames_rejected": rx.get("rejected"),
        "deadline_misses": ctl.get("deadline_misses"),
        "missed_periods": ctl.get("missed_periods"),
        "stale_features": ctl.get("stale_features"),
        "vision_scheduling": v.get("scheduling"),
        "roi": _roi_counters(cam, v),
        "J": ctl.get("J"),
        "problems": ctl.get("problems", []),
        "vision_reported": bool(v),
        "vision_tail": run["vision_tail"],
        "exit_codes": run["exit_codes"],
    }


LOCKSTEP_RUNS = {
    "image": {"camera.model": "image"},
    "image_clean": {"camera.model": "image", **CLEAN_CAMERA},
    "image_no_log": {"camera.model": "image", "camera.image_log_fps": 0.0},
    "analytic": {"camera.model": "analytic"},
}
"""The lockstep runs compared: images (with the configured image log), images of a clean camera
(:data:`CLEAN_CAMERA`, the image log on), images with no image log (what logging what the
camera saw costs), the analytic camera."""


def lockstep_speed(cfg: RigConfig, duration_s: float, law: str = "ioc") -> dict[str, Any]:
    """A lockstep rig run of each of :data:`LOCKSTEP_RUNS` (``hil bench loop``'s lockstep
    measurement): speed against real time, the period's wall time and where it goes."""
    import tempfile

    from rt_controller.rig.bench_loop import bench_lockstep

    out: dict[str, Any] = {}
    for name, overrides in LOCKSTEP_RUNS.items():
        with tempfile.TemporaryDirectory(prefix=f"hil-bench-vision-{name}-") as work:
            run = bench_lockstep(cfg.with_overrides(overrides), duration_s, law, Path(work))
        out[name] = {
            k: run[k] for k in ("sim_s", "ticks", "speedup_loop", "speedup_total", "period_us", "J")
        }
    clean, analytic = out["image_clean"]["J"], out["analytic"]["J"]
    both = isinstance(clean, int | float) and isinstance(analytic, int | float) and analytic
    out["image_clean"]["J_vs_analytic"] = clean / analytic - 1.0 if both else None
    return out


def bench_vision(
    cfg: RigConfig,
    render: Render,
    truth: Truth,
    *,
    grid: int = 7,
    latency_frames: int = 300,
    fps: float = 60.0,
    lockstep_s: float = 5.0,
    realtime_s: float = 10.0,
    progress: Callable[[str], None] = lambda s: None,
) -> dict[str, Any]:
    """Every figure of the module docstring, as one JSON-ready dict."""
    poses = pose_grid(cfg, grid)
    out: dict[str, Any] = {"poses": len(poses), "sizes": {}}
    for w, h in SIZES:
        progress(f"timing {w}x{h}")
        sized = cfg.with_overrides({"camera.width_px": w, "camera.height_px": h})
        out["sizes"][f"{w}x{h}"] = timing(sized, render, poses)
    still = np.zeros(2)
    noiseless = cfg.with_overrides(NO_NOISE)
    progress("accuracy")
    out["accuracy"] = {
        "no_noise": accuracy(noiseless, render, truth, poses, still),
        "default_noise": accuracy(cfg, render, truth, poses, still),
    }
    progress("blur at peak speed")
    out["blur"] = {
        "dq": list(PEAK_DQ),
        "exposure_s": cfg.camera.exposure_s,
        **accuracy(cfg, render, truth, poses, np.array(PEAK_DQ)),
    }
    if latency_frames > 0:
        progress("latency over zenoh")
        out["latency"] = latency(cfg, render, latency_frames, fps)
    if lockstep_s > 0:
        progress(f"lockstep rigs of {lockstep_s:g} s: images, clean, unlogged, analytic")
        out["lockstep"] = lockstep_speed(cfg, lockstep_s)
        progress(f"lockstep rig of {lockstep_s:g} s with images: where a period goes")
        out["lockstep_profile"] = lockstep_profile(cfg, lockstep_s)
    if realtime_s > 0:
        progress(f"realtime rig of {realtime_s:g} s with images at {fps:g} fps")
        out["realtime"] = realtime_pipeline(cfg, realtime_s, fps)
    return out
