"""How close a number computed on this machine must be to one recorded on another.

**Same machine, same build: bit for bit.** A deterministic run (closed loop, lockstep rig, replay
of a log on the machine that replays it) is a function of its inputs and of the machine code numba
compiled here, so two runs, in one process or in two, are equal to the last bit. Tests of that kind
compare with ``==`` and must keep doing so.

**A constant recorded on another machine: never bit for bit.** numba compiles for the host CPU
(``NUMBA_CPU_NAME`` defaults to it), and the RHC kernels use ``fastmath`` ``contract`` and
``reassoc``: LLVM fuses multiply-adds (FMA) and reorders sums for the vector width (SSE2, AVX2,
AVX-512, NEON), so the last digits of one tick differ between CPUs. The inverse-optimal law, the
model kernels and the emulator physics are compiled without fastmath and came out bit-identical
in every build measured; closed-loop RHC amplifies a rounding-level difference, most after the
target jump at 3 s, when the long horizons' residual spikes (to ~1e2).

Measured with ``python -m tests.support.cross_cpu OUT_DIR`` on an AMD EPYC (Zen 4, AVX-512),
each build in its own process with a fresh ``NUMBA_CACHE_DIR``: ``generic`` (= ``x86-64``, SSE2,
no FMA: the build the goldens are pinned to), native (= ``znver4``), ``x86-64`` + FMA (128-bit
vectors with FMA, as on ARM), ``haswell`` (= ``znver3``), ``skylake-avx512`` (= ``x86-64-v4``; it
reproduces the goldens pinned before, recorded on such an Intel CPU, to the last bit), ``generic``
with glibc's libm FMA variants and NumPy's AVX dispatch off, the NumPy reference solver
(``tests/support/rhc_reference.py``), and q0 nudged by one ulp. The largest relative spread of J
in the default RHC loop (T = 0.1 s, N = 10, what ``hil simulate --law rhc`` runs) was 2.7e-8; the
inverse-optimal loop's 7.4e-16 (the ulp nudge only). Per-golden figures are beside the goldens in
``tests/controller/test_rhc_closed_loop.py``.

A tolerance is about 15-30x the largest spread measured, and still an order of magnitude or more
below what a deliberate change moves: ``gains.kp`` changed by 1e-4 relative moves J by 4.6e-5
(RHC) and 4.8e-5 (IOC), ``robot.m2`` by 1e-4 moves it by 2.2e-5, ``rhc.kmax`` 5 -> 6 by 4.1e-5.
"""

from __future__ import annotations

IOC_J_REL = 1e-12
"""Relative tolerance on J of the inverse-optimal closed loop against a recorded constant.
Spread 0 across all builds, 7.4e-16 from a one-ulp nudge of q0; the margin covers a libm that
rounds sin/cos differently in the last bit (ARM)."""

RHC_J_REL = 5e-7
"""Relative tolerance on J of the default RHC closed loop (T = 0.1 s, N = 10, 6 s of the paper
scenario, 50 Hz) against a recorded constant. Spread 2.7e-8 (native Zen 4 vs generic; the
reference solver 2.1e-8, skylake-avx512 4.1e-9), so 19x; kp + 1e-4 moves J by 4.6e-5."""
