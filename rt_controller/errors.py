"""Exception tree of the controller package."""

from __future__ import annotations


class ControllerError(Exception):
    """Root of every error raised by :mod:`rt_controller`."""


class ControllerConfigError(ControllerError, ValueError):
    """A command-line option or setting is invalid (the message names it)."""


class OutputPathError(ControllerConfigError):
    """An output file or folder given on the command line cannot be written (names the option,
    the path and why); raised before the command starts its work."""


class LogError(ControllerError, OSError):
    """An MCAP log could not be written or read."""


class MissingExtraError(ControllerError, ImportError):
    """An optional dependency is not installed; the message names the extra that brings it
    (``pip install 'hil-rhc-visual-servo[analysis]'``)."""


class NotAHilLogError(LogError):
    """An MCAP file that holds no controller run (written by another tool, or cut before its
    first record)."""
