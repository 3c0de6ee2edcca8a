"""Fault injection of ``hil vision --dropout START:DURATION``: a window of simulation time
without features. One type for both vision processes (the analytic one,
:mod:`plant_emulator.vision_node`, and the image pipeline, :mod:`vision.grabber`), so both accept
and refuse the same windows."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from hal.arguments import MAX_DURATION_S
from hal.errors import HalConfigError


def _refuse(got: str) -> HalConfigError:
    return HalConfigError(
        f"--dropout must be START:DURATION in seconds of simulation time, 0 <= START <= "
        f"{MAX_DURATION_S:g} and 0 < DURATION <= {MAX_DURATION_S:g} (e.g. 1.0:0.5), got {got!r}"
    )


@dataclass(frozen=True)
class Dropout:
    """No features for frames delivered in ``[start_s, start_s + duration_s)`` of simulation
    time; both bounded by :data:`~hal.arguments.MAX_DURATION_S` (finite nanoseconds)."""

    start_s: float
    duration_s: float

    def __post_init__(self) -> None:
        start, length = self.start_s, self.duration_s
        if not (0 <= start <= MAX_DURATION_S and 0 < length <= MAX_DURATION_S):  # NaN too
            raise _refuse(f"{start:g}:{length:g}")

    @classmethod
    def parse(cls, text: str) -> Dropout:
        """``"START:DURATION"`` in seconds, e.g. ``"1.0:0.5"``; a bad window is one line."""
        start, sep, length = text.strip().partition(":")
        try:
            if not sep:
                raise ValueError
            values = float(start), float(length)
        except ValueError:
            raise _refuse(text) from None
        try:
            return cls(*values)
        except HalConfigError:
            raise _refuse(text) from None

    @property
    def start_ns(self) -> int:
        return round(self.start_s * 1e9)

    @property
    def end_ns(self) -> int:
        return round((self.start_s + self.duration_s) * 1e9)

    def contains(self, sim_ns: int) -> bool:
        return self.start_ns <= sim_ns < self.end_ns

    def __str__(self) -> str:
        return f"{self.start_s:g}:{self.duration_s:g}"


def in_dropout(dropouts: Sequence[Dropout], sim_ns: int) -> bool:
    """Whether simulation time ``sim_ns`` falls into one of the ``dropouts``."""
    return any(d.contains(sim_ns) for d in dropouts)


__all__ = ["Dropout", "in_dropout"]
