"""The study spec of ``hil sweep``: expansion, seeds, and bad specs refused before any run."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest

from rt_controller.sweep.spec import SweepSpecError, load_spec, run_seed, spec_from_dict

GOOD = {
    "study": {"duration_s": 1.0, "repetitions": 3},
    "base": {"camera": {"noise_px": 0.5}, "controller": {"law": "ioc"}},
    "axes": [
        {"key": "plant.z_wo", "values": [0.9, 1.0, 1.1]},
        {"key": "plant.theta1", "distribution": "uniform", "low": 0.8, "high": 1.2, "samples": 4},
        {"key": "gains.kp", "distribution": "log-uniform", "low": 0.05, "high": 0.3, "samples": 4},
    ],
}


ANALYTIC_NOISE = {"noise_px": 0.5, "model": "analytic"}
"""Pixel noise on the camera that applies it on both engines."""


def test_grid_times_draws_times_repetitions():
    spec = spec_from_dict(GOOD)
    assert len(spec.points) == 3 * 4 and spec.runs == 36
    tasks = spec.tasks()
    assert len(tasks) == 36 and len({t.key for t in tasks}) == 36
    assert [p["plant.z_wo"] for p in spec.points[:5]] == [0.9] * 4 + [1.0]
    for p in spec.points:
        assert 0.8 <= p["plant.theta1"] <= 1.2 and 0.05 <= p["gains.kp"] <= 0.3
    # the draws are joint: every grid value meets the same Monte Carlo samples
    assert [p["plant.theta1"] for p in spec.points[:4]] == [
        p["plant.theta1"] for p in spec.points[4:8]
    ]
    t = tasks[5]
    assert t.config["plant"]["z_wo"] == t.axes["plant.z_wo"]
    assert t.config["camera"]["seed"] == t.seed == run_seed(spec.spec_hash, t.point, t.rep)


def test_seeds_and_draws_depend_on_the_spec_only():
    a, b = spec_from_dict(GOOD), spec_from_dict(GOOD)
    assert a.spec_hash == b.spec_hash and a.points == b.points
    assert [t.key for t in a.tasks()] == [t.key for t in b.tasks()]
    seeds = [t.seed for t in a.tasks()]
    assert len(set(seeds)) == len(seeds)
    other = spec_from_dict({**GOOD, "study": {"duration_s": 2.0, "repetitions": 3}})
    assert other.spec_hash != a.spec_hash
    # the engine is not part of the spec hash: the same point gets the same seed on both
    c = spec_from_dict({**GOOD, "base": {**GOOD["base"], "camera": ANALYTIC_NOISE}})
    sim, rig = c.tasks("simulate"), c.tasks("rig")
    assert [t.seed for t in sim] == [t.seed for t in rig]
    assert {t.key for t in sim}.isdisjoint(t.key for t in rig)


def test_horizon_axis_follows_the_rules_of_the_horizon_option():
    spec = spec_from_dict({"axes": [{"key": "rhc.horizon", "values": [0.1, 1.0]}]})
    steps = [t.config["rhc"]["steps"] for t in spec.tasks()]
    assert steps == [10, 20]  # N = max(rhc.steps, ceil(T / 0.05)), as --horizon


def test_normal_draws_are_truncated_to_their_bounds():
    spec = spec_from_dict(
        {
            "axes": [
                {
                    "key": "plant.z_wo",
                    "distribution": "normal",
                    "mean": 1.0,
                    "std": 0.5,
                    "low": 0.9,
                    "high": 1.1,
                    "samples": 50,
                }
            ]
        }
    )
    values = [p["plant.z_wo"] for p in spec.points]
    assert len(values) == 50 and all(0.9 <= v <= 1.1 for v in values)


def _with_axis(axis: dict) -> dict:
    return {"axes": [axis]}


@pytest.mark.parametrize(
    ("data", "needle"),
    [
        (_with_axis({"key": "plant.mass", "values": [1.0]}), "unknown key plant.mass"),
        (_with_axis({"key": "nosuch.key", "values": [1.0]}), "unknown config key 'nosuch.key'"),
        (_with_axis({"key": "rhc.steps", "values": [10, 1000000000]}), "out of range"),
        (_with_axis({"key": "plant.z_wo", "values": [1.0, 50.0]}), "plant.z_wo"),
        (_with_axis({"key": "plant.theta1", "values": [0.5]}), "inertia I1"),
        (_with_axis({"key": "plant.z_wo", "distribution": "uniform", "samples": 3}), "and high"),
        (
            _with_axis(
                {"key": "plant.z_wo", "distribution": "normal", "mean": 1, "std": 0.1, "samples": 3}
            ),
            "needs low and high",
        ),
        (
            _with_axis(
                {
                    "key": "plant.z_wo",
                    "distribution": "uniform",
                    "low": 0.5,
                    "high": 20,
                    "samples": 5,
                }
            ),
            "plant.z_wo",
        ),
        (_with_axis({"key": "plant.z_wo", "distribution": "cauchy"}), "distribution: must be"),
        (_with_axis({"key": "plant.z_wo", "values": []}), "non-empty list"),
        (_with_axis({"key": "camera.seed", "values": [1, 2]}), "repetitions set camera.seed"),
        ({"study": {"repetitions": 0}}, "study.repetitions"),
        ({"study": {"duration": 1.0}}, "unknown key study.duration"),
        ({"study": {"engine": "matlab"}}, "study.engine"),
        ({"base": {"robot": {"m9": 1.0}}}, "unknown key robot.m9"),
        ({"base": {"nosuch": {}}}, "unknown section [base.nosuch]"),
        ({"axis": []}, "unknown table(s) axis"),
        (
            {
                "axes": [
                    {"key": "plant.z_wo", "values": [1.0]},
                    {"key": "plant.z_wo", "values": [1.1]},
                ]
            },
            "given twice",
        ),
    ],
)
def test_bad_specs_are_refused(data, needle):
    with pytest.raises(SweepSpecError) as info:
        spec_from_dict(data)
    assert needle in str(info.value)
    assert "\n" not in str(info.value)


def test_a_bad_spec_is_one_line_and_exit_2_before_any_run(tmp_path: Path):
    spec = tmp_path / "bad.toml"
    spec.write_text('[[axes]]\nkey = "plant.z_wo"\ndistribution = "uniform"\nsamples = 4\n')
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "rt_controller.cli", "sweep", str(spec), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("hil sweep: error: ")
    assert "low and high" in lines[0] and str(spec) in lines[0]
    assert not out.exists()


def test_spec_file_with_a_base_config(tmp_path: Path):
    (tmp_path / "rig.toml").write_text("[controller]\nlaw = 'pbc'\n")
    (tmp_path / "s.toml").write_text(
        '[study]\nconfig = "rig.toml"\nduration_s = 0.5\n[base.camera]\nnoise_px = 0.25\n'
    )
    spec = load_spec(tmp_path / "s.toml")
    assert spec.base.controller.law == "pbc" and spec.base.camera.noise_px == 0.25
    assert spec.runs == 1 and math.isclose(spec.study.duration_s, 0.5)


def test_a_hardware_profile_runs_on_the_rig_engine_only():
    """hardware.profile (an axis or the base's key) reaches each rig run's config; the
    simulate engine drives no hardware, so a cia402 point is refused there, in one line."""
    axis = {"axes": [{"key": "hardware.profile", "values": ["dsp", "cia402"]}]}
    spec = spec_from_dict(axis)
    assert [t.config["hardware"]["profile"] for t in spec.tasks("rig")] == ["dsp", "cia402"]
    assert spec.hardware_profiles() == ["cia402", "dsp"]
    with pytest.raises(SweepSpecError, match=r"point 1: hardware\.profile = 'cia402' needs"):
        spec.tasks("simulate")
    base = spec_from_dict({"base": {"hardware": {"profile": "cia402"}}})
    assert base.hardware_profiles() == ["cia402"]
    with pytest.raises(SweepSpecError, match="--engine rig"):
        base.tasks()
    assert len(spec_from_dict({}).tasks("simulate")) == 1  # the default dsp profile


def test_pixel_noise_runs_on_the_simulate_engine_or_the_analytic_camera():
    """camera.noise_px is the analytic camera's: the simulate engine applies it; a rig run on
    the rendering camera would not, so such a point is refused on the rig engine."""
    spec = spec_from_dict(GOOD)
    assert spec.tasks("simulate")[0].config["camera"]["noise_px"] == 0.5
    with pytest.raises(SweepSpecError, match=r"point 0 on the rig engine: camera\.noise_px"):
        spec.tasks("rig")
    analytic = spec_from_dict({**GOOD, "base": {"camera": ANALYTIC_NOISE}})
    assert len(analytic.tasks("rig")) == len(spec.tasks("simulate"))


def test_every_shipped_sweep_example_loads_and_its_runs_validate():
    """The studies under ``examples/`` that the docs run (``hil sweep examples/X.toml``)."""
    from pathlib import Path

    from rt_controller.sweep.spec import load_spec

    root = Path(__file__).resolve().parents[2] / "examples"
    studies = [p for p in sorted(root.glob("*.toml")) if "[study]" in p.read_text()]
    assert {p.name for p in studies} >= {"robustness.toml", "profiles.toml"}
    for path in studies:
        spec = load_spec(str(path))
        assert spec.tasks(), path.name  # every run's config built and validated
