"""Control laws by name: the one table (python-can's ``BACKENDS`` is the model).

Each entry maps a law name to ``(module, class)``; the module is imported only when the law is
built, so ``hil --help`` and the closed-form laws never load the C/GMRES solver. The names
themselves are :data:`hal.config.LAW_NAMES` (config validation and the CLI's ``--law`` choices
use them; ``hal`` may not import this package), and a test checks the two agree.

To add a law: write a class with ``name``, ``__call__(Measurement) -> LawOutput`` and
``reset()`` whose constructor takes ``(model, cfg)``, add it here and its name to
``hal.config.LAW_NAMES``.
"""

from __future__ import annotations

import importlib

from hal.config import LAW_NAMES, RigConfig
from rt_controller.control.laws import ControlLaw
from rt_controller.control.model import NominalModel
from rt_controller.errors import ControllerConfigError

LAWS: dict[str, tuple[str, str]] = {
    "pbc": ("rt_controller.control.laws", "PassivityBasedLaw"),
    "ioc": ("rt_controller.control.laws", "InverseOptimalLaw"),
    "rhc": ("rt_controller.control.rhc.law", "RecedingHorizonLaw"),
}
"""Law name -> (module, class); the class is built as ``cls(model, cfg)``."""


def make_law(name: str, model: NominalModel, cfg: RigConfig) -> ControlLaw:
    """The law called ``name`` (one of :data:`hal.config.LAW_NAMES`) for this model and config."""
    try:
        module, cls_name = LAWS[name]
    except KeyError:
        raise ControllerConfigError(
            f"unknown law {name!r} (choose from {', '.join(LAW_NAMES)})"
        ) from None
    return getattr(importlib.import_module(module), cls_name)(model, cfg)
