"""``hil up`` on images (camera.model = "image", the default): the emulated camera renders, the
vision process measures f from the pixels. Lockstep is bit-exact for a seed and, with noise,
blur and distortion off, has the analytic camera's J to 0.5 %; a realtime run is clean with
f_first at the paper's (-120, -160); ``hil replay`` reproduces an image run exactly."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.support import run_hil

pytestmark = pytest.mark.integration

CLEAN = (
    "[camera]\nlens_k1 = 0.0\nlens_k2 = 0.0\nexposure_s = 0.0\n"
    "electrons_per_dn = 0.0\nread_noise_dn = 0.0\n"
)
ANALYTIC = '[camera]\nmodel = "analytic"\n'


def up(tmp_path: Path, name: str, *args: str, config: str | None = None) -> dict:
    extra = []
    if config is not None:
        path = tmp_path / f"{name}.toml"
        path.write_text(config)
        extra = ["--config", str(path)]
    log = tmp_path / f"{name}.mcap"
    proc = run_hil(
        ["up", *args, "--duration", "4", "--json", "--log", str(log), *extra], timeout_s=300
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads(proc.stdout)
    summary["log_path"] = str(log)
    return summary


def test_lockstep_on_images_is_bit_exact_and_replays_exactly(tmp_path):
    a = up(tmp_path, "a", "--lockstep")
    b = up(tmp_path, "b", "--lockstep")
    assert a["J"] == b["J"] and a["f_final"] == b["f_final"]
    # default lens and sensor noise: 0.015 px at q(0) (measured)
    assert a["f_first"] == pytest.approx([-120.0, -160.0], abs=0.05)
    assert a["jump_seen_s"] is not None and a["stale_features"] == 0
    proc = run_hil(["replay", a["log_path"], "--tol", "1e-9", "--json", "-q"], timeout_s=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert json.loads(proc.stdout)["matches"] is True
    # what the camera saw is in the log (10 fps of sim time: t = 0, 0.1, ..., 4.0 s), and the
    # pipeline re-run offline on those frames finds the target in every one
    proc = run_hil(["vision", "--source", f"log:{a['log_path']}", "--json"], timeout_s=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rerun = json.loads(proc.stdout.strip().splitlines()[-1])
    assert rerun["frames"] == rerun["valid"] == 41
    # --frames: one JSON line a frame on stdout, a JSON-lines stream (the summary on stderr)
    proc = run_hil(["vision", "--source", f"log:{a['log_path']}", "--frames"], timeout_s=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    frames = [json.loads(line) for line in proc.stdout.splitlines()]
    assert len(frames) == 41 and all(f["valid"] for f in frames)
    assert "41 frames from" in proc.stderr and "0 without the target, " in proc.stderr


def test_clean_images_give_the_analytic_j(tmp_path):
    image = up(tmp_path, "image", "--lockstep", config=CLEAN)
    analytic = up(tmp_path, "analytic", "--lockstep", config=ANALYTIC)
    # measured over 10 s: 23.8837 against 23.8968 (-0.055 %)
    assert image["J"] == pytest.approx(analytic["J"], rel=0.005)


def test_realtime_on_images_is_clean(tmp_path):
    s = up(tmp_path, "rt")
    assert s["clock"] == "realtime" and s["stale_features"] == 0
    assert s["f_first"] == pytest.approx([-120.0, -160.0], abs=1.0)
