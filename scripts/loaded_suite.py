#!/usr/bin/env python3
"""Run the test suite several times in a row on a deliberately loaded machine; report flips.

Usage::

    .venv/bin/python scripts/loaded_suite.py [--runs 3] [--hogs 2] [--out DIR] [-- PYTEST_ARGS...]

Starts ``--hogs`` CPU hogs (busy loops in child processes, default 2: as many as this machine
has cores), then runs ``python -m pytest -m "not vcan" PYTEST_ARGS`` ``--runs`` times in a row,
each with a JUnit XML report in ``--out``. Prints one JSON object: each run's summary (passed,
failed, skipped, errors, xfailed, wall seconds, load average) and every test whose outcome is
not the same in all runs. Exits 1 when a test flipped or any run failed, else 0. The hogs are
stopped on every exit path.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _hog() -> None:  # pragma: no cover - runs in a child process until killed
    x = 0
    while True:
        x = (x * 1103515245 + 12345) & 0xFFFFFFFF


def outcomes(junit: Path) -> dict[str, str]:
    """``{test id: passed | failed | error | skipped | xfailed}`` from a JUnit XML report."""
    out: dict[str, str] = {}
    for case in ET.parse(junit).getroot().iter("testcase"):
        name = f"{case.get('classname', '')}::{case.get('name', '')}"
        kinds = {child.tag for child in case}
        skipped = case.find("skipped")
        if "failure" in kinds:
            out[name] = "failed"
        elif "error" in kinds:
            out[name] = "error"
        elif skipped is not None:
            xfail = (skipped.get("type") or "") == "pytest.xfail"
            out[name] = "xfailed" if xfail else "skipped"
        else:
            out[name] = "passed"
    return out


def flips(runs: list[dict[str, str]]) -> dict[str, list[str | None]]:
    """Tests whose outcome is not the same in every run (missing in a run counts as None)."""
    names = sorted(set().union(*runs)) if runs else []
    return {n: [r.get(n) for r in runs] for n in names if len({r.get(n) for r in runs}) > 1}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--runs", type=int, default=3, help="runs of the suite in a row (default: %(default)s)"
    )
    ap.add_argument(
        "--hogs", type=int, default=2, help="CPU hogs beside the runs (default: %(default)s)"
    )
    ap.add_argument(
        "--out",
        default="loaded-suite",
        help="directory for the JUnit reports, relative to the current one (default: %(default)s)",
    )
    ap.add_argument(
        "pytest_args",
        nargs="*",
        help='extra pytest arguments, after `--` (pytest always gets -m "not vcan")',
    )
    args = ap.parse_args(argv)
    if args.runs < 1 or args.hogs < 0:
        ap.error("--runs must be >= 1 and --hogs >= 0")
    out = Path(args.out).resolve()  # pytest runs in the repository: the caller's folder here
    out.mkdir(parents=True, exist_ok=True)
    # SIGTERM unwinds like Ctrl-C, so the hogs are stopped by the ``finally`` below
    signal.signal(signal.SIGTERM, lambda signum, _frame: sys.exit(128 + signum))
    hogs = [multiprocessing.Process(target=_hog, daemon=True) for _ in range(args.hogs)]
    for h in hogs:
        h.start()
    summaries, results = [], []
    try:
        for i in range(1, args.runs + 1):
            junit = out / f"run{i}.xml"
            cmd = [sys.executable, "-m", "pytest", "-q", "-m", "not vcan", f"--junitxml={junit}"]
            t0 = time.monotonic()
            # pytest's own output goes to stderr: stdout carries only the JSON result
            proc = subprocess.run(
                [*cmd, *args.pytest_args], cwd=REPO, check=False, stdout=sys.stderr
            )
            wall = time.monotonic() - t0
            res = outcomes(junit) if junit.exists() else {}
            results.append(res)
            counts = {k: sum(v == k for v in res.values()) for k in set(res.values())}
            summaries.append(
                {
                    "run": i,
                    "exit_status": proc.returncode,
                    "wall_s": round(wall, 1),
                    "load_1min": os.getloadavg()[0],
                    **dict(sorted(counts.items())),
                }
            )
            print(f"loaded_suite: run {i}: {json.dumps(summaries[-1])}", file=sys.stderr)
    finally:
        for h in hogs:
            h.kill()
            h.join()
    flipped = flips(results)
    print(json.dumps({"hogs": args.hogs, "runs": summaries, "flipped": flipped}, indent=1))
    bad_run = any(s["exit_status"] != 0 for s in summaries) or not all(results)
    return 1 if flipped or bad_run else 0


if __name__ == "__main__":
    sys.exit(main())
