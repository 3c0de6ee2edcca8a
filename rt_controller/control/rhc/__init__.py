"""Receding-horizon control (eq. 30) solved on-line by C/GMRES (Ohtsuka 2004).

:class:`RecedingHorizonLaw` is the control law; :class:`CGMRESSolver` the compiled solver and
:class:`~rt_controller.control.rhc.reference.ReferenceSolver` its plain-NumPy twin.
"""

from rt_controller.control.rhc.law import RecedingHorizonLaw
from rt_controller.control.rhc.solver import CGMRESSolver, SolveReport

__all__ = ["CGMRESSolver", "RecedingHorizonLaw", "SolveReport"]
