"""Exception tree of the hardware abstraction layer.

Every error raised by :mod:`hal` derives from :class:`HalError`; each subclass also inherits the
builtin exception a caller would naturally catch (``TimeoutError``, ``ValueError``, ...).
"""

from __future__ import annotations


class HalError(Exception):
    """Root of every error raised by the hardware abstraction layer."""


class HalConfigError(HalError, ValueError):
    """A configuration value is missing, of the wrong type or out of range (names the key)."""


class HalTimeoutError(HalError, TimeoutError):
    """The other side (DSP, vision) stayed silent for longer than allowed."""


class HalTransportError(HalError, OSError):
    """A bus or session could not be opened or used; the message says what to do about it."""


class HalCodecError(HalError, ValueError):
    """A frame or message could not be encoded or decoded (bad CRC, length, counter, schema)."""


class HalStopped(HalError, InterruptedError):
    """A wait was abandoned because the caller asked to stop (not a failure of the other side)."""


class HalDriveError(HalError, RuntimeError):
    """A CANopen drive did not take a configuration step or a state change (names the node and
    the object or state); the message says what to check on the drive."""
