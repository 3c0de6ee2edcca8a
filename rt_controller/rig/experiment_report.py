"""Everything ``hil experiment`` writes: figures (:mod:`~rt_controller.rig.experiment_figures`),
``results.json`` (:mod:`~rt_controller.rig.experiment_results`) and ``report.md``
(:mod:`~rt_controller.rig.experiment_markdown`), turned out of the runs of
:mod:`rt_controller.rig.experiment` by :func:`write_outputs`.
"""

from __future__ import annotations

import json
from typing import Any

from hal.strict_json import finite
from hal.whole_file import written_whole
from rt_controller.rig.experiment import RunResult, RunSpec, Settings, plan
from rt_controller.rig.experiment_figures import FIGURE_FILES, write_figures
from rt_controller.rig.experiment_markdown import render_report
from rt_controller.rig.experiment_results import build_results, initial_4v


def write_outputs(
    settings: Settings,
    runs_by_exp: dict[str, list[RunSpec]],
    runs: dict[str, RunResult],
    command: str,
) -> dict[str, Any]:
    """Figures, ``results.json`` and ``report.md`` in the output folder; returns the results."""
    figures = write_figures(settings, runs_by_exp, runs)
    res = finite(build_results(settings, runs_by_exp, runs, command, figures))
    res["report"] = str(settings.out / "report.md")
    res["results"] = str(settings.out / "results.json")
    # each written whole (hal.whole_file): a full disk or a kill leaves no half file
    with written_whole(settings.out / "results.json") as tmp:
        tmp.write_text(json.dumps(res, indent=2) + "\n", encoding="utf-8")
    with written_whole(settings.out / "report.md") as tmp:
        tmp.write_text(render_report(res, initial_4v(runs)), encoding="utf-8")
    return res


def clear_earlier(settings: Settings) -> list[str]:
    """``--force``, before any run: remove what an earlier experiment wrote in the output
    folder that this one writes anew (``results.json``, ``report.md``, the figures, and the
    logs and plans of the runs it plans), so that a run killed or failing before its write-up
    leaves no earlier results to be read as its own. Nothing else is touched: the logs of runs
    not planned now, rerun logs, files the experiment does not write. Returns what went
    (paths relative to the output folder)."""
    out = settings.out
    names = {s.name for specs in plan(settings, settings.base_config()).values() for s in specs}
    known = [
        "results.json",
        "report.md",
        *FIGURE_FILES,
        *(f"logs/{n}.mcap" for n in sorted(names)),
        *(f"plans/{n}.json" for n in sorted(names)),
    ]
    gone = []
    for rel in known:
        path = out / rel
        if path.is_file() or path.is_symlink():
            path.unlink()
            gone.append(rel)
    return gone
