"""Measure the cross-CPU spread of the closed-loop goldens (a tool, not a test).

numba compiles for the host CPU: FMA, vector width and, with the RHC kernels' ``fastmath``
``contract``/``reassoc``, the order of sums depend on it, so a deterministic run is bit-identical
on one machine but not across machines. This tool runs every golden of
``tests/controller/test_rhc_closed_loop.py`` once per *build*, each build in its own process with
its own fresh ``NUMBA_CACHE_DIR`` (so caches never mix), and prints the relative spread of J, of
J before the target jump and of the final f, around the generic build the goldens are pinned to::

    .venv/bin/python -m tests.support.cross_cpu OUT_DIR            # measure all builds
    .venv/bin/python -m tests.support.cross_cpu OUT_DIR --table    # print the table only

A build is an environment: ``NUMBA_CPU_NAME`` (``NUMBA_CPU_FEATURES=""`` makes LLVM take the
named CPU's own features; unset, numba would keep the host's), glibc's and NumPy's CPU dispatch
turned down, or the Python rule on the NumPy reference solver (``tests/support/rhc_reference.py``)
in place of the compiled one.
Builds for CPUs the host cannot execute are skipped (``/proc/cpuinfo`` flags). Two rounding-level
nudges (q0 moved by one ulp) and deliberate parameter changes are run natively for comparison:
a tolerance must cover the first and catch the second.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from tests.support import REPO

JUMP_S = 3.0
"""The paper scenario's target jump: J before it is far less sensitive to rounding."""

RUNS: dict[str, tuple[str, float, dict]] = {
    # name: (law, duration s, overrides), as in tests/controller/test_rhc_closed_loop.py
    "ioc": ("ioc", 6.0, {}),
    "T0.02": ("rhc", 6.0, {"rhc.horizon": 0.02}),
    "T0.1N10": ("rhc", 6.0, {"rhc.horizon": 0.1, "rhc.steps": 10}),
    "T1N50": ("rhc", 6.0, {"rhc.horizon": 1.0, "rhc.steps": 50}),
    "T1N10": ("rhc", 6.0, {"rhc.horizon": 1.0, "rhc.steps": 10}),
    "growth": ("rhc", 6.0, {"rhc.horizon": 0.1, "rhc.horizon_growth": 5.0}),
    "umax1": ("rhc", 8.0, {"rhc.u_max": [1.0, 0.5], "scenario.disturbance": False}),
    "umax05": ("rhc", 8.0, {"rhc.u_max": [0.5, 0.2], "scenario.disturbance": False}),
    "umax2": ("rhc", 6.0, {"rhc.u_max": [2.0, 1.0], "scenario.disturbance": False}),
}

_SSE4 = "+sse2,+sse3,+ssse3,+sse4.1,+sse4.2"
BUILDS: dict[str, tuple[dict[str, str], list[str], set[str]]] = {
    # name: (environment, extra arguments, /proc/cpuinfo flags the build needs)
    "native": ({}, [], set()),
    "generic": ({"NUMBA_CPU_NAME": "generic"}, [], set()),
    "x86-64+fma": (
        {"NUMBA_CPU_NAME": "x86-64", "NUMBA_CPU_FEATURES": _SSE4 + ",+fma"},
        [],
        {"fma"},
    ),  # FMA with 128-bit vectors: what an ARM (NEON) build looks like
    "haswell": ({"NUMBA_CPU_NAME": "haswell", "NUMBA_CPU_FEATURES": ""}, [], {"avx2", "fma"}),
    "skylake-avx512": (
        {"NUMBA_CPU_NAME": "skylake-avx512", "NUMBA_CPU_FEATURES": ""},
        [],
        {"avx512f", "avx512bw", "avx512vl", "avx512dq"},
    ),
    "znver3": ({"NUMBA_CPU_NAME": "znver3", "NUMBA_CPU_FEATURES": ""}, [], {"avx2", "vaes"}),
    "znver4": (
        {"NUMBA_CPU_NAME": "znver4", "NUMBA_CPU_FEATURES": ""},
        [],
        {"avx512f", "avx512_bf16", "avx512vbmi"},
    ),
    "x86-64-v4": (
        {"NUMBA_CPU_NAME": "x86-64-v4", "NUMBA_CPU_FEATURES": ""},
        [],
        {"avx512f", "avx512bw", "avx512vl", "avx512dq"},
    ),
    "generic-all-down": (
        {
            "NUMBA_CPU_NAME": "generic",
            "GLIBC_TUNABLES": "glibc.cpu.hwcaps=-AVX2,-FMA,-AVX512F",
            "NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL",
        },
        [],
        set(),
    ),  # libm without its FMA variants, NumPy at its SSE4 baseline
    "reference": ({}, ["--reference"], set()),
}
NUDGES: dict[str, list[str]] = {
    "ulp-q0": ["--ulp-q0"],  # rounding level: another CPU's rounding is of this kind
    "kp+1e-4": ["--perturb", "gains.kp=0.130013"],
    "kp+1e-3": ["--perturb", "gains.kp=0.13013"],
    "m2+1e-4": ["--perturb", "robot.m2=2.04600458"],
    "dummy_weight+1e-4": ["--perturb", "rhc.dummy_weight=0.010001"],
    "kmax 6": ["--perturb", "rhc.kmax=6"],
}


def cpu_flags() -> set[str]:
    try:
        text = Path("/proc/cpuinfo").read_text(encoding="utf-8")
    except OSError:
        return set()
    for line in text.splitlines():
        if line.startswith(("flags", "Features")):
            return set(line.split(":", 1)[1].split())
    return set()


def run_one(out: Path, args: list[str]) -> dict:
    """Every golden in this process (its numba build): J, J before the jump, final f."""
    import numpy as np

    from hal.config import load_config
    from plant_emulator.world import World
    from rt_controller.control.controller import Controller
    from rt_controller.control.model import NominalModel
    from rt_controller.control.simulate import run_closed_loop
    from tests.support.python_laws import RecedingHorizonLaw
    from tests.support.python_rule import PythonRule
    from tests.support.rhc_reference import ReferenceSolver

    perturb: dict = {}
    if "--perturb" in args:
        key, value = args[args.index("--perturb") + 1].split("=")
        perturb[key] = json.loads(value)
    if "--ulp-q0" in args:
        q0 = list(load_config().scenario.q0)
        q0[0] = float(np.nextafter(q0[0], np.inf))
        perturb["scenario.q0"] = q0
    runs = {}
    for name, (law, duration, overrides) in RUNS.items():
        cfg = load_config().with_overrides({**overrides, **perturb})
        c: Controller | PythonRule = Controller(cfg, law)
        if law == "rhc" and "--reference" in args:  # the Python rule on the NumPy solver
            model = NominalModel.from_config(cfg)
            c = PythonRule(cfg, RecedingHorizonLaw(model, cfg, solver=ReferenceSolver(model, cfg)))
        r = run_closed_loop(World(cfg), c, cfg, duration)
        runs[name] = {
            "J": r.J,
            "J_before_jump": before_jump(r),
            "f": [float(v) for v in r.trace.f[-1]],
            "fallbacks": r.as_dict()["fallbacks"],
        }
    out.write_text(json.dumps({"args": args, "runs": runs}, indent=1), encoding="utf-8")
    return runs


def before_jump(r) -> float:
    """J of the ticks before the target jump (``SimResult.J``'s sum, cut at ``JUMP_S``)."""
    import numpy as np

    t = r.trace.array("t")
    return float(np.sum(np.asarray(r.trace.cost)[t < JUMP_S - 1e-9]) / r.rate)


def measure(out_dir: Path) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    flags = cpu_flags()
    jobs = {b: (env, args) for b, (env, args, need) in BUILDS.items() if need <= flags}
    jobs |= {n: ({}, args) for n, args in NUDGES.items()}
    for name, (env, args) in jobs.items():
        cache = tempfile.mkdtemp(prefix=f"numba-{name}-")
        full = {**os.environ, **env, "NUMBA_CACHE_DIR": cache}
        cmd = [sys.executable, "-m", "tests.support.cross_cpu", "--one", str(out_dir / name)]
        rc = subprocess.run([*cmd, *args], env=full, cwd=REPO, check=False).returncode
        print(name, "rc", rc, flush=True)


def table(out_dir: Path) -> None:
    from tests.controller.test_rhc_closed_loop import GOLDEN

    got = {p.name: json.loads(p.read_text(encoding="utf-8"))["runs"] for p in out_dir.iterdir()}
    builds = [b for b in BUILDS if b in got]
    for qty in ("J", "J_before_jump", "f"):
        print(f"\n{qty}: relative to the pinned golden (abs px for f); spread = max over builds")
        print(f"{'golden':8s} " + " ".join(f"{b[:10]:>10s}" for b in builds + list(NUDGES)))
        for name in RUNS:
            pin = getattr(GOLDEN[name], qty)
            cells = []
            for b in builds + list(NUDGES):
                if b not in got:
                    cells.append("-")
                    continue
                v = got[b][name][qty]
                if qty == "f":
                    cells.append(f"{max(abs(v[0] - pin[0]), abs(v[1] - pin[1])):.1e}")
                else:
                    cells.append(f"{(v - pin) / pin:+.1e}")
            print(f"{name:8s} " + " ".join(f"{c:>10s}" for c in cells))


def main(argv: list[str]) -> int:
    if argv[0] == "--one":
        run_one(Path(argv[1]), argv[2:])
        return 0
    out_dir = Path(argv[0])
    if "--table" not in argv:
        measure(out_dir)
    table(out_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
