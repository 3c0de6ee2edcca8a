"""The tutorial notebook ``examples/analyse_a_log.ipynb`` runs from top to bottom (nbclient), so
it cannot rot: it records a short lockstep run with ``hil up``, loads it, draws the paper's
Fig. 3 in at most five lines of code, shows the other tables and calls ``hil info`` and
``hil export``."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from rt_controller.logs import load
from tests.support import REPO, hil_command

NOTEBOOK = REPO / "examples" / "analyse_a_log.ipynb"

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def test_the_tutorial_notebook_runs(tmp_path, monkeypatch):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    # `hil` of this environment first on the kernel's PATH (as in an activated venv)
    hil_dir = Path(hil_command()[0]).parent if len(hil_command()) == 1 else Path(sys.executable)
    monkeypatch.setenv("PATH", f"{hil_dir}{os.pathsep}{os.environ.get('PATH', '')}")
    nb = nbformat.read(NOTEBOOK, as_version=4)
    assert all(not c.get("outputs") for c in nb.cells if c.cell_type == "code"), "stored clean"
    client = nbclient.NotebookClient(
        nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    )
    client.execute()

    figure = next(c for c in nb.cells if c.cell_type == "code" and ".plot(" in c.source)
    lines = [ln for ln in figure.source.splitlines() if ln.strip() and not ln.startswith("#")]
    assert len(lines) <= 5, lines
    assert any("image/png" in out.get("data", {}) for out in figure.outputs)

    log = tmp_path / "tutorial.mcap"
    run = load(log)
    assert not run.truncated and len(run.cycles) == 200 and set(run.cycles["law"]) == {"rhc"}
    assert (tmp_path / "tutorial.mat").exists()
    shell = nb.cells[-1].outputs[0]["text"]
    assert "problems:        none" in shell and "/controller/cycle" in shell
