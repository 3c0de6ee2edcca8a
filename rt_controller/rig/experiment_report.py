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
from rt_controller.rig.experiment import RunResult, RunSpec, Settings
from rt_controller.rig.experiment_figures import write_figures
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
