"""The emulated DSP for a clock mode: :func:`make_dsp` picks the runner."""

from __future__ import annotations

from typing import Any

from plant_emulator.dsp_lockstep import LockstepDsp
from plant_emulator.dsp_node import DspNode
from plant_emulator.dsp_realtime import RealtimeDsp


def make_dsp(cfg: Any, bus: Any, *, lockstep: bool = False, **kwargs: Any) -> DspNode:
    """A :class:`~plant_emulator.dsp_lockstep.LockstepDsp` (steps on Sync) or a
    :class:`~plant_emulator.dsp_realtime.RealtimeDsp` (its own frame clock) on ``bus``;
    ``kwargs`` are the runner's options."""
    runner = LockstepDsp if lockstep else RealtimeDsp
    return runner(cfg, bus, **kwargs)
