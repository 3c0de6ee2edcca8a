"""``hil report --plot``'s contact sheet: the camera frames a log holds (``/camera/image``,
:mod:`rt_controller.monitor.camera_view`) around the target jump, with what the detector made of
each (``/camera/detection``).

The jump's time is the scenario's ``jump_time`` in simulation time; a frame is placed on the
same axis by the sim time its ``/vision/features`` record carries (the same capture stamp), else
through the cycle records (a frame's log time is its capture stamp, a cycle's its tick, both
CLOCK_MONOTONIC shifted by the log's ``monotonic_to_unix_ns``). A run without a jump, or one
that ended before it, has no sheet.
"""

from __future__ import annotations

import bisect
import re
from pathlib import Path
from typing import Any

import numpy as np

from hal.log_topics import DETECTION_TOPIC, IMAGE_TOPIC, VISION_TOPIC
from hal.whole_file import written_whole
from rt_controller.logtools.reader import LoadedLog
from rt_controller.logtools.walk import topic_messages

FRAMES = 8
"""Frames on the sheet: the four before the jump and the four from it on."""
_LABEL = re.compile(rb"frame \d+: (detected f = \([^)]*\) px|no target: [a-z_]+)")


def frames_around(log: LoadedLog, t_jump_s: float, n: int = FRAMES) -> list[dict[str, Any]]:
    """Up to ``n`` frames around simulation time ``t_jump_s``: ``{"t_s", "pixels", "label"}``
    (``t_s`` in simulation time); empty when the log holds no frames or no cycles, or when its
    frames do not span ``t_jump_s`` (a run that ended before the jump has no frames of it)."""
    from vision.sources import decode_compressed_image

    sim = log.cycles.get("sim_time_s")
    t_ns = log.cycles.get("t_ns")
    try:  # hil.run metadata is text: a damaged or foreign value means no time axis
        offset = int(log.run_info["monotonic_to_unix_ns"])
    except (KeyError, TypeError, ValueError):
        return []
    if sim is None or t_ns is None or len(sim) == 0:
        return []
    cyc_log = np.asarray(t_ns, dtype=np.int64) + offset
    images: list[tuple[int, bytes]] = []
    labels: dict[int, str] = {}
    shown: dict[int, float] = {}  # log time (capture stamp) -> the sim time the frame shows
    # the stream reader, as far as the file goes: a log whose writer was killed has no summary
    for topic, msg in topic_messages(log.path, (IMAGE_TOPIC, DETECTION_TOPIC, VISION_TOPIC)):
        if topic == IMAGE_TOPIC:
            images.append((msg.log_time, msg.data))
        elif topic == VISION_TOPIC:
            if (at := _features_sim_time(msg.data)) is not None:
                shown[max(0, at[0] + offset)] = at[1]
        else:
            m = _LABEL.search(msg.data)
            labels[msg.log_time] = m.group(1).decode(errors="replace") if m else ""
    if not images or not labels:  # no frames, or only an analytic run's blank image plane
        return []
    images.sort(key=lambda item: item[0])
    # simulation time of each frame: the one its features carry (same capture stamp; a
    # lockstep frame is rendered before the tick that steps to it), else the cycles' sim time
    # interpolated at its log time
    order = np.argsort(cyc_log)
    t_frames = np.interp([lt for lt, _ in images], cyc_log[order], np.asarray(sim)[order])
    t_frames = np.array([shown.get(lt, t) for (lt, _), t in zip(images, t_frames, strict=True)])
    by_time = np.argsort(t_frames, kind="stable")
    images, t_frames = [images[i] for i in by_time], t_frames[by_time]
    if not t_frames[0] <= t_jump_s <= t_frames[-1]:  # the run ended before the jump
        return []
    at = bisect.bisect_left(list(t_frames), t_jump_s)
    lo = max(0, at - n // 2)
    chosen = range(lo, min(len(images), lo + n))
    out = []
    for i in chosen:
        log_time, data = images[i]
        pixels = decode_compressed_image(data)
        if pixels is not None:
            out.append(
                {"t_s": float(t_frames[i]), "pixels": pixels, "label": labels.get(log_time, "")}
            )
    return out


def _features_sim_time(data: bytes) -> tuple[int, float] | None:
    """``(capture stamp ns, sim time s)`` of one logged ``/vision/features`` record (JSON with
    the base64 payload), None for one that does not decode."""
    import base64
    import json

    from hal.vision_codec import decode_features

    try:
        rec = json.loads(data)
        msg = decode_features(base64.b64decode(rec["data"], validate=True))
    except (ValueError, TypeError, KeyError):  # HalCodecError and bad base64 are ValueErrors
        return None
    return msg.stamp_ns, msg.sim_time_ns / 1e9


def write_contact_sheet(log: LoadedLog, path: Path) -> bool:
    """Draw the sheet into ``path`` (PNG); False when the log has no frames to show, or no
    target jump (``scenario.disturbance = false``, or the run ended before ``jump_time``)."""
    from matplotlib.figure import Figure

    if log.config is not None and not log.config.scenario.disturbance:
        return False  # the target never jumped: no sheet "around the target jump"
    jump = log.config.scenario.jump_time if log.config is not None else 3.0
    frames = frames_around(log, jump)
    if not frames:
        return False
    cols = 4
    rows = (len(frames) + cols - 1) // cols
    fig = Figure(figsize=(3.2 * cols, 2.8 * rows), layout="constrained")
    fig.suptitle(f"What the camera saw around the target jump (t = {jump:g} s)")
    for k, fr in enumerate(frames):
        ax = fig.add_subplot(rows, cols, k + 1)
        ax.imshow(fr["pixels"], cmap="gray", vmin=0, vmax=255)
        ax.set_title(f"t ~ {fr['t_s']:.2f} s\n{fr['label']}", fontsize=7)
        ax.set_axis_off()
    with written_whole(path) as tmp:  # a full disk: no half PNG, the last one stays
        fig.savefig(tmp, dpi=100, format="png")
    return True
