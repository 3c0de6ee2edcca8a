"""Start-up of the rig's daemon processes without what they never use.

numba looks for a BLAS the first time it compiles or loads a kernel, by importing
``scipy.linalg`` when SciPy is installed (it is a test dependency here): about 0.3 s of CPU and
tens of MB of shared libraries in every process that uses numba, paid again by every run of
``hil experiment``. The rig's kernels call no BLAS (``@`` and ``np.dot`` on arrays are written
out; ``tests/emulator/test_without_scipy.py`` runs them where SciPy cannot be imported), so
``hil controller`` and ``hil emulator`` skip it.
"""

from __future__ import annotations

import sys

BLOCKED = "scipy.linalg"


def without_scipy_linalg() -> bool:
    """Make ``import scipy.linalg`` fail in this process (call it before numba is imported).

    Returns whether it took effect: False when ``scipy.linalg`` is already imported (then
    nothing changes). numba then compiles kernels without BLAS support, which the rig's
    kernels do not need.
    """
    if BLOCKED in sys.modules:
        return False
    sys.modules[BLOCKED] = None  # type: ignore[assignment]  # import raises ImportError
    return True


__all__ = ["without_scipy_linalg"]
