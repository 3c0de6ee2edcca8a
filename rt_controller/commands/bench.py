"""``hil bench``: performance measurements printed as JSON (never asserted in tests)."""

from __future__ import annotations

import argparse
import json

from rt_controller.commands.common import add_config_option, config_from_args


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="measure solver and loop performance (JSON)")
    bench = p.add_subparsers(dest="bench", metavar="WHAT", required=True)
    s = bench.add_parser("solver", help="C/GMRES update time on the paper scenario closed loop")
    add_config_option(s)
    s.add_argument("--updates", type=int, default=2000, help="updates per configuration")
    s.add_argument("--json", action="store_true", help="print one JSON object (always JSON)")
    s.set_defaults(handler=run_solver)


def run_solver(args: argparse.Namespace) -> int:
    from rt_controller.bench_solver import bench_solver

    cfg = config_from_args(args)
    print(json.dumps(bench_solver(cfg, updates=args.updates)))
    return 0
