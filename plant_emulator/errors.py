"""Exception tree of the plant emulator."""

from __future__ import annotations

from hal.errors import HalError


class EmulatorError(HalError):
    """Root of every error raised by :mod:`plant_emulator`."""


class PhysicsError(EmulatorError, ArithmeticError):
    """The arm's state became non-finite (the integration diverged)."""


class CameraSensorError(EmulatorError, ValueError):
    """The camera's settings cannot make an image (e.g. a lens that cannot be inverted)."""
