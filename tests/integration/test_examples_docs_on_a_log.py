"""The code the log tutorials print runs as written on a fresh log, so the docs cannot rot:
the Python blocks of ``docs/tutorials/analyse-a-log.md`` (column names, ``arrays()`` keys, the
config fields), the clip-making script of ``docs/tutorials/real-camera.md`` and the ``hil info``
line the analysis tutorial quotes. One short lockstep run (the notebook's command, 2 s) feeds
them all; ``tests/integration/test_notebook.py`` holds the notebook itself."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support import REPO, hil_command

ANALYSE = REPO / "docs" / "tutorials" / "analyse-a-log.md"
CAMERA = REPO / "docs" / "tutorials" / "real-camera.md"

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def python_blocks(md: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", md.read_text(encoding="utf-8"), flags=re.S)


def run_python(code: str, cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "MPLBACKEND": "Agg"}
    return subprocess.run(
        [sys.executable, "-", *args], input=code, cwd=cwd, env=env,
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    """A folder holding ``run.mcap``: 2 s of the paper scenario, RHC, lockstep."""
    work = tmp_path_factory.mktemp("docs-log")
    cmd = [*hil_command(), "up", "--lockstep", "--law", "rhc", "--duration", "2"]
    done = subprocess.run(
        [*cmd, "--log", "run.mcap", "--json"], cwd=work, capture_output=True, text=True,
        timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert json.loads(done.stdout)["problems"] == []
    return work


def test_the_analysis_tutorials_python_blocks_run_on_a_log(folder):
    blocks = python_blocks(ANALYSE)
    assert len(blocks) >= 2 and all('load("run.mcap")' in b for b in blocks)
    for block in blocks:
        done = run_python(block, folder)
        assert done.returncode == 0, f"{block}\n{done.stderr[-2000:]}"


def test_the_hil_info_line_the_tutorial_quotes_is_the_one_it_prints(folder):
    """The tutorial quotes the parameter requests' line of ``hil info``: same label."""
    quoted = re.search(
        r"`([a-z ]+): \d+ accepted, \d+ refused, \d+ unauthenticated`", ANALYSE.read_text()
    )
    assert quoted, "the tutorial no longer quotes the line"
    info = subprocess.run(
        [*hil_command(), "info", "run.mcap"], cwd=folder, capture_output=True, text=True,
        timeout=120,
    )  # fmt: skip
    assert info.returncode == 0, info.stderr
    labels = {ln.split(":", 1)[0] for ln in info.stdout.splitlines() if "accepted" in ln}
    assert quoted.group(1) in labels, (quoted.group(0), info.stdout)


def test_the_camera_tutorials_clip_script_makes_a_clip_of_every_logged_frame(folder):
    cv2 = pytest.importorskip("cv2")
    from mcap.reader import make_reader

    text = CAMERA.read_text(encoding="utf-8")
    script = re.search(r"python - clip-run\.mcap <<'PY'\n(.*?)\nPY\n", text, flags=re.S)
    assert script, "the tutorial no longer holds the clip script"
    done = run_python(script.group(1), folder, "run.mcap")
    assert done.returncode == 0, done.stderr[-2000:]
    with (folder / "run.mcap").open("rb") as fh:
        logged = sum(1 for _ in make_reader(fh).iter_messages(topics=["/camera/image"]))
    clip = cv2.VideoCapture(str(folder / "clip.mp4"))
    frames = 0
    while clip.read()[0]:
        frames += 1
    clip.release()
    assert logged > 0 and frames == logged
