"""The compile target of numba's code: what a log records of it, and compiling for it again.

numba compiles for the CPU it runs on: LLVM picks instructions (FMA or not, vector widths) and
their order by CPU name and feature set, so the same law on the same inputs rounds differently
on another CPU (an RHC log from an AMD Zen 4 replayed on an Intel host: max |dtau| 2.9e-6).
A run records the target its code was compiled for (:func:`run_info`, in ``hil.run``), and
the versions that change rounding besides it (numba, llvmlite, LLVM, numpy, Python, glibc).

glibc picks its libm's code (sin, cos, exp...) by the CPU at run time, whatever numba compiled
for: with FMA and AVX2 it runs variants that round differently (a replay with glibc told the
CPU has no FMA, AVX2 or AVX differs by 1.1e-10 for ``generic`` code and 1.8e-5 for ``znver4``
code: RHC amplifies the last bit). :func:`run_info` records the features that choice uses
(``libm_cpu_features``) and :func:`libm_env` narrows glibc's choice to the recording host's.

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
KEY_LIBM = "libm_cpu_features"
LIBM_FEATURES = {"avx": "AVX", "avx2": "AVX2", "fma": "FMA", "fma4": "FMA4"}
"""CPU features (LLVM's names) by which glibc picks its x86-64 libm variants, with the names
``GLIBC_TUNABLES=glibc.cpu.hwcaps=-NAME`` takes."""
ENV_TUNABLES = "GLIBC_TUNABLES"
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
    """The ``hil.run`` entries of this process's compile target, libm features and versions."""
    target = this_process()
    return {
        KEY_NAME: target.cpu_name,
        KEY_FEATURES: target.features,
        KEY_TRIPLE: target.triple,
        KEY_LIBM: ",".join(sorted(libm_features())),
        **versions(),
    }


def _hwcaps_off(tunables: str) -> set[str]:
    """The ``glibc.cpu.hwcaps=-NAME`` entries of a ``GLIBC_TUNABLES`` value."""
    off: set[str] = set()
    for item in tunables.split(":"):
        key, _, value = item.partition("=")
        if key == "glibc.cpu.hwcaps":
            off |= {v[1:] for v in value.split(",") if v.startswith("-")}
    return off


def libm_features() -> set[str]:
    """The features of :data:`LIBM_FEATURES` glibc's libm uses in this process: the host's,
    less those ``GLIBC_TUNABLES`` turns off."""
    off = _hwcaps_off(os.environ.get(ENV_TUNABLES, ""))
    host = host_features()
    return {f for f, name in LIBM_FEATURES.items() if f in host and name not in off}


def libm_matches(info: dict[str, str]) -> bool:
    """This process's libm picks the variants the log's host picked (True when the log
    does not say)."""
    if KEY_LIBM not in info:
        return True
    return libm_features() == {f for f in info[KEY_LIBM].split(",") if f}


def libm_env(info: dict[str, str]) -> tuple[dict[str, str], list[str]]:
    """For a process that should pick the libm variants the log's host picked: the
    ``GLIBC_TUNABLES`` that turns off what this host has beyond it (empty when nothing is), and
    the features the log's host used that this one lacks (those variants cannot run here)."""
    if KEY_LIBM not in info:
        return {}, []
    logged = {f for f in info[KEY_LIBM].split(",") if f}
    host = {f for f in LIBM_FEATURES if f in host_features()}
    extra, missing = sorted(host - logged), sorted(logged - host)
    if not extra:
        return {}, missing
    hwcaps = "glibc.cpu.hwcaps=" + ",".join(f"-{LIBM_FEATURES[f]}" for f in extra)
    current = os.environ.get(ENV_TUNABLES, "")
    return {ENV_TUNABLES: f"{current}:{hwcaps}" if current else hwcaps}, missing


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
