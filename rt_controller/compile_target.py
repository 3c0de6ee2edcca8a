"""The compile target of numba's code: what a log records of it, and compiling for it again.

numba compiles for the CPU it runs on: LLVM picks instructions (FMA or not, vector widths) and
their order by CPU name and feature set, so the same law on the same inputs rounds differently
on another CPU (an RHC log from an AMD Zen 4 replayed on an Intel host: max |dtau| 2.9e-6).
A run records the target its code was compiled for (:func:`run_info`, in ``hil.run``), and
the versions that change rounding besides it (numba, llvmlite, LLVM, numpy, Python, glibc).

A recorded :class:`CompileTarget` can be compiled for again on any host that has every CPU
feature it enables (:meth:`CompileTarget.runnable`): numba reads ``NUMBA_CPU_NAME`` and
``NUMBA_CPU_FEATURES`` once, when it is imported, so that code runs in a new process with
:meth:`CompileTarget.env`, which also gives each target its own numba cache
(:func:`cache_dir`) so targets never evict each other's compiled code.
"""

from __future__ import annotations

import hashlib
import os
import platform
from dataclasses import dataclass
from functools import cache
from pathlib import Path

ENV_NAME = "NUMBA_CPU_NAME"
ENV_FEATURES = "NUMBA_CPU_FEATURES"
ENV_CACHE = "NUMBA_CACHE_DIR"
KEY_NAME = "numba_cpu_name"
KEY_FEATURES = "numba_cpu_features"
KEY_TRIPLE = "numba_target_triple"
VERSION_KEYS = (
    "numba_version",
    "llvmlite_version",
    "llvm_version",
    "numpy_version",
    "python_version",
    "glibc_version",
)
"""``hil.run`` keys of the versions that can change rounding (besides the CPU target)."""
GENERIC = "generic"
"""LLVM's portable x86-64 target (SSE2, no FMA): runs on every x86-64 host."""


@dataclass(frozen=True)
class CompileTarget:
    """What numba compiles for: LLVM's target triple, CPU name and flattened feature string
    (``+avx2,-amx-tile,...``; empty for ``generic``)."""

    cpu_name: str
    features: str
    triple: str = ""

    @property
    def enabled(self) -> frozenset[str]:
        """The features this target may use (the ``+`` entries)."""
        return frozenset(f[1:] for f in self.features.split(",") if f.startswith("+"))

    def missing_here(self) -> list[str]:
        """Enabled features this host's CPU lacks (sorted); empty when it can run the code."""
        return sorted(self.enabled - host_features())

    def runnable(self) -> bool:
        """This host can run code compiled for this target (same triple, every feature)."""
        same_triple = not self.triple or self.triple == this_process().triple
        return same_triple and not self.missing_here()

    def env(self) -> dict[str, str]:
        """The environment that makes a new process's numba compile for this target, in this
        target's own cache."""
        return {
            ENV_NAME: self.cpu_name,
            ENV_FEATURES: self.features,
            ENV_CACHE: str(cache_dir(self)),
        }

    def label(self) -> str:
        """``znver4`` or ``generic``, with a short digest of the features when they are not
        the host's own (two hosts' ``skylake-avx512`` may differ in features)."""
        if self.features == "" or self.features == host_feature_string():
            return self.cpu_name
        return f"{self.cpu_name} (features {digest(self.features)})"

    def as_dict(self) -> dict[str, str]:
        return {"cpu_name": self.cpu_name, "features": self.features, "triple": self.triple}


def digest(text: str) -> str:
    """A short stable digest (12 hex digits) of ``text``."""
    return hashlib.sha256(text.encode()).hexdigest()[:12]


@cache
def host_feature_string() -> str:
    """This host CPU's features as LLVM flattens them (what numba uses by default)."""
    import llvmlite.binding as ll

    try:
        return ll.get_host_cpu_features().flatten()
    except RuntimeError:  # LLVM cannot tell on this host
        return ""


def host_features() -> frozenset[str]:
    """The features this host's CPU has."""
    return CompileTarget("host", host_feature_string()).enabled


def this_process() -> CompileTarget:
    """The target numba compiles for in this process (from its code generator, so
    ``NUMBA_CPU_NAME``/``NUMBA_CPU_FEATURES`` and ``NUMBA_ENABLE_AVX`` are accounted for)."""
    from numba.core.registry import cpu_target

    triple, name, features = cpu_target.target_context.codegen().magic_tuple()
    return CompileTarget(str(name), str(features), str(triple))


def host_native() -> CompileTarget:
    """This host's own target (what numba compiles for with no NUMBA_CPU_* variables)."""
    import llvmlite.binding as ll

    return CompileTarget(ll.get_host_cpu_name(), host_feature_string(), this_process().triple)


def generic() -> CompileTarget:
    """The portable target (:data:`GENERIC`, no features)."""
    return CompileTarget(GENERIC, "", this_process().triple)


def cache_dir(target: CompileTarget) -> Path:
    """numba's cache for code compiled for ``target``, under the user's cache folder
    (``$XDG_CACHE_HOME`` or ``~/.cache``): ``hil/numba/<cpu>-<features digest>``."""
    root = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(root) / "hil" / "numba" / f"{target.cpu_name}-{digest(target.features)}"


def versions() -> dict[str, str]:
    """The versions of :data:`VERSION_KEYS` in this process."""
    import llvmlite
    import llvmlite.binding as ll
    import numba
    import numpy as np

    libc, libc_version = platform.libc_ver()
    return {
        "numba_version": numba.__version__,
        "llvmlite_version": llvmlite.__version__,
        "llvm_version": ".".join(str(v) for v in ll.llvm_version_info),
        "numpy_version": np.__version__,
        "python_version": platform.python_version(),
        "glibc_version": libc_version if libc == "glibc" else f"{libc or 'unknown'} {libc_version}",
    }


def run_info() -> dict[str, str]:
    """The ``hil.run`` entries of this process's compile target and versions."""
    target = this_process()
    return {
        KEY_NAME: target.cpu_name,
        KEY_FEATURES: target.features,
        KEY_TRIPLE: target.triple,
        **versions(),
    }


def recorded(info: dict[str, str]) -> CompileTarget | None:
    """The compile target a log's ``hil.run`` records (None: a log from before it did)."""
    name = info.get(KEY_NAME)
    if not name:
        return None
    return CompileTarget(name, info.get(KEY_FEATURES, ""), info.get(KEY_TRIPLE, ""))


def version_changes(info: dict[str, str]) -> list[str]:
    """``numba 0.60.0 -> 0.68.1`` for each rounding-relevant version the log recorded that
    differs in this process."""
    here = versions()
    return [
        f"{key.removesuffix('_version')} {info[key]} -> {here[key]}"
        for key in VERSION_KEYS
        if info.get(key) and info[key] != here[key]
    ]
