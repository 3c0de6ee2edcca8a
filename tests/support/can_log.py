"""A small log of raw CAN frames, written through the recorder's public seam
(:class:`CycleRecorder`) with frames encoded by the rig's codecs: Sync frames (``Tick``,
``Counter``) between JointPosition frames (``Q1``, ``Q2``, ``Sample``, no ``Tick``), so
``Tick`` is present in some rows and absent in the others."""

from __future__ import annotations

from pathlib import Path

from hal.can_codec import DspCodec
from hal.config import RigConfig
from rt_controller.runtime.recorder import CycleRecorder

T0_NS = 1_000_000_000
TICKS = (4_294_967_295, 4_294_967_294, 123_456_789)
"""The Sync ticks (the widest integer signal of hal/hil.dbc: 32 bits)."""


def write_tick_log(path: Path) -> Path:
    """``path``: one Sync of each of :data:`TICKS`, each followed by a JointPosition."""
    dsp = DspCodec()
    info = {"clock": "lockstep", "can": "virtual", "zenoh": "tcp/127.0.0.1:1", "recorder": "thread"}
    with CycleRecorder(path, RigConfig(), run_info=info) as rec:
        for i, tick in enumerate(TICKS):
            rec.record_can(dsp.encode_sync(tick), T0_NS + 2 * i * 1000, "rx")
            position, _ = dsp.encode_state((0.25, -0.5), (0.0, 0.0), i)
            rec.record_can(position, T0_NS + (2 * i + 1) * 1000, "rx")
    return path
