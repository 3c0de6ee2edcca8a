"""The ``[hardware]`` section: which hardware profile the controller drives (and the
emulator emulates)."""

from __future__ import annotations

from dataclasses import dataclass

PROFILES = ("dsp", "cia402")
"""The hardware profiles behind the controller's seam (:mod:`hal.hardware_interface`)."""


@dataclass(frozen=True)
class HardwareConfig:
    """The rig's hardware."""

    profile: str = "dsp"
    """dsp (our DSP: hal/hil.dbc over CAN FD, E2E and SecOC; the default) | cia402 (two
    CANopen CiA 402 drives in cyclic synchronous torque, ``[cia402]``; CANopen has no MAC, so
    the CAN side of this profile is NOT authenticated)."""
