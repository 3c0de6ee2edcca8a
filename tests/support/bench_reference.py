"""What compiling buys: the NumPy reference solver (:mod:`tests.support.rhc_reference`, a test
oracle) against the compiled one, on ``hil bench solver``'s closed loop.

``python -m tests.support.bench_reference [--updates N] [--reference-updates M]`` prints one
JSON object: both solvers' median and p99 update time (µs) and their ratio. Timings are noisy on
a shared machine; this is a benchmark, never a test assertion.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from hal.config import RigConfig, load_config
from rt_controller.control.model import NominalModel
from rt_controller.control.rhc.solver import CGMRESSolver
from rt_controller.rig.bench_solver import nominal_plant_step, run_updates, summary
from tests.support.rhc_reference import ReferenceSolver


def bench_reference(cfg: RigConfig, updates: int = 500, reference_updates: int = 100) -> dict:
    """The two solvers' update times on the same closed loop (``updates`` and
    ``reference_updates`` ticks), and the ratio of their medians."""
    model = NominalModel.from_config(cfg)
    step = nominal_plant_step(model, cfg)
    compiled = CGMRESSolver(model, cfg)
    compiled.warm_up()
    fast = summary(cfg, run_updates(compiled, model, cfg, step, updates))
    ref = summary(
        cfg, run_updates(ReferenceSolver(model, cfg), model, cfg, step, reference_updates)
    )
    out: dict[str, Any] = {}
    for name, s in (("compiled", fast), ("numpy_reference", ref)):
        out[name] = {
            "updates": s["updates"],
            "solve_us": {"median": s["solve_us"]["median"], "p99": s["solve_us"]["p99"]},
        }
    out["ratio"] = ref["solve_us"]["median"] / fast["solve_us"]["median"]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--updates", type=int, default=500)
    ap.add_argument("--reference-updates", type=int, default=100)
    args = ap.parse_args(argv)
    print(json.dumps(bench_reference(load_config(), args.updates, args.reference_updates)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
