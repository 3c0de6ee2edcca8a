"""Optional dependencies (the package's extras) and the one error a missing one gives.

Every job that needs a module of an extra imports it through :func:`require` (or checks the
whole extra up front with :func:`require_extra`); ``cli.main`` turns a stray
:class:`ModuleNotFoundError` of such a module into the same error (:func:`as_missing_extra`).
Either way the user reads one line naming the extra and the pip command, and ``hil`` exits 2.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from rt_controller.errors import MissingExtraError

PACKAGE = "hil-rhc-visual-servo"

EXTRAS: dict[str, tuple[str, ...]] = {
    "analysis": ("pandas", "pyarrow", "scipy"),
    "sweep": ("distributed", "dask", "pandas", "pyarrow"),
    "docs": ("mkdocs", "material", "mkdocstrings"),
}
"""The top-level modules each extra of ``pyproject.toml`` brings (the ones the code imports)."""


def install_command(extra: str) -> str:
    """``pip install 'hil-rhc-visual-servo[EXTRA]'``."""
    return f"pip install '{PACKAGE}[{extra}]'"


def extra_of(module: str) -> str | None:
    """The first extra (in :data:`EXTRAS` order) that brings ``module``'s top-level package."""
    top = module.split(".")[0]
    return next((name for name, mods in EXTRAS.items() if top in mods), None)


def missing(module: str, what: str, extra: str) -> MissingExtraError:
    """The one-line error: ``WHAT needs the 'EXTRA' extra (MODULE is not installed): pip ...``."""
    top = module.split(".")[0]
    return MissingExtraError(
        f"{what} needs the '{extra}' extra ({top} is not installed): {install_command(extra)}"
    )


def require(module: str, what: str, extra: str | None = None) -> ModuleType:
    """Import ``module`` of an extra (``extra``, default: the one that brings it), or raise
    :class:`MissingExtraError` naming the extra and its pip command (``what`` is the job that
    needed it, e.g. ``"hil sweep"``)."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        name = extra or extra_of(module)
        if name is None:
            raise
        raise missing(module, what, name) from exc


def require_extra(extra: str, what: str) -> None:
    """Import every module of ``extra`` now, before any work (a study must not fail after its
    first run because a module it needs later is missing)."""
    for module in EXTRAS[extra]:
        require(module, what, extra)


def as_missing_extra(exc: ModuleNotFoundError, what: str) -> MissingExtraError | None:
    """The :class:`MissingExtraError` for ``exc`` when the module it could not find belongs to
    an extra, else None (a module of the core install is missing: a broken install, whose
    traceback is the useful report)."""
    name = exc.name or ""
    extra = extra_of(name)
    return missing(name, what, extra) if name and extra else None
