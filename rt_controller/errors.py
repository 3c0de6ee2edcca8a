"""Exception tree of the controller package."""

from __future__ import annotations


class ControllerError(Exception):
    """Root of every error raised by :mod:`rt_controller`."""


class ControllerConfigError(ControllerError, ValueError):
    """A command-line option or setting is invalid (the message names it)."""


class SolverError(ControllerError, ArithmeticError):
    """The receding-horizon solver could not produce a usable solution."""


class LogError(ControllerError, OSError):
    """An MCAP log could not be written or read."""
