"""Receding-horizon control (eq. 30) solved on-line by C/GMRES (Ohtsuka 2004).

:class:`RecedingHorizonLaw` is the control law, :class:`CGMRESSolver` the compiled solver (its
plain-NumPy twin is a test oracle, ``tests/support/rhc_reference.py``).
"""

from rt_controller.control.rhc.law import RecedingHorizonLaw
from rt_controller.control.rhc.solver import CGMRESSolver, SolveReport

__all__ = ["CGMRESSolver", "RecedingHorizonLaw", "SolveReport"]
