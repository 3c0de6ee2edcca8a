"""``hil controller --plan``: the plan file's rules and the command line (no processes)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hal.config import RigConfig, load_config
from hal.sim_control import SEED_MAX
from rt_controller.cli import main
from rt_controller.config_rules import config_toml
from rt_controller.errors import ControllerConfigError
from rt_controller.runtime.plan import (
    first_difference,
    load_plan,
    reset_seed,
    run_configs,
    world_of,
)


def write(tmp_path: Path, doc: object, name: str = "plan.json") -> Path:
    path = tmp_path / name
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc), encoding="utf-8")
    return path


def run_entry(tmp_path: Path, name: str, cfg: RigConfig | None = None, **kw: object) -> dict:
    conf = tmp_path / f"{name}.toml"
    conf.write_text(config_toml(cfg or load_config(None)), encoding="utf-8")
    entry = {"name": name, "config": str(conf), "log": str(tmp_path / f"{name}.mcap")}
    return {**entry, "duration_s": 1.0, **kw}


def test_a_plan_reads_back_its_runs(tmp_path):
    runs = [run_entry(tmp_path, "a", law="rhc"), run_entry(tmp_path, "b", duration_s=2)]
    plan = load_plan(write(tmp_path, {"runs": runs}))
    assert [(r.name, r.law, r.duration_s) for r in plan] == [("a", "rhc", 1.0), ("b", None, 2.0)]
    assert plan[1].log == tmp_path / "b.mcap"


@pytest.mark.parametrize(
    ("doc", "words"),
    [
        ("{", "not JSON"),
        ({"runs": []}, "non-empty list"),
        ([1, 2], "non-empty list"),
        ({"runs": [3]}, "run 0: must be an object"),
        ({"runs": [{"name": "a", "config": "c", "log": "l"}]}, "duration_s"),
        ({"runs": [{"name": "a", "config": "c", "log": "l", "duration_s": 0}]}, "duration_s"),
        ({"runs": [{"name": "a", "config": "c", "log": "l", "duration_s": True}]}, "duration_s"),
        ({"runs": [{"name": "a", "config": "", "log": "l", "duration_s": 1}]}, "'config'"),
        ({"runs": [{"name": "a", "config": "c", "log": "l", "duration_s": 1, "x": 1}]}, "'x'"),
        ({"runs": [{"name": "a", "config": "c", "log": "l", "duration_s": 1, "law": 3}]}, "law"),
        (
            {"runs": [{"name": "a", "config": "c", "log": "l", "duration_s": 1}] * 2},
            "names must be unique",
        ),
        (
            {
                "runs": [
                    {"name": n, "config": "c", "log": "same.mcap", "duration_s": 1}
                    for n in ("a", "b")
                ]
            },
            "same log",
        ),
    ],
)
def test_a_bad_plan_is_refused_naming_what_is_wrong(tmp_path, doc, words):
    with pytest.raises(ControllerConfigError, match=words):
        load_plan(write(tmp_path, doc))


def test_a_missing_plan_file_is_a_clear_error(tmp_path):
    with pytest.raises(ControllerConfigError, match="cannot read"):
        load_plan(tmp_path / "nope.json")


def test_runs_may_differ_in_the_controllers_sections_and_a_resettable_seed_only(tmp_path):
    """The controller's sections and a camera seed that fits hal.sim_control.SEED_MAX (the reset
    carries it) may differ between runs; anything else the emulator or vision reads may not,
    nor may a seed beyond 32 bits."""
    base = load_config(None)
    ok = base.with_overrides(
        {"controller.law": "pbc", "rhc.horizon": 1.0, "gains.kp": 0.2, "camera.seed": SEED_MAX}
    )
    bad = base.with_overrides({"camera.noise_px": 0.7})
    assert first_difference(world_of(base), world_of(ok)) is None
    assert first_difference(world_of(base), world_of(bad)) == "camera.noise_px"
    assert reset_seed(ok) == SEED_MAX and reset_seed(base) == base.camera.seed
    big = base.with_overrides({"camera.seed": SEED_MAX + 1})
    assert reset_seed(big) is None
    assert first_difference(world_of(base), world_of(big)) == "camera.seed"
    runs = load_plan(
        write(
            tmp_path,
            {
                "runs": [
                    run_entry(tmp_path, "a", base),
                    run_entry(tmp_path, "b", ok, law="ioc"),
                    run_entry(tmp_path, "c", bad),
                ]
            },
        )
    )
    cfgs = run_configs(runs[:2], lambda c: c)
    assert [c.controller.law for c in cfgs] == [base.controller.law, "ioc"]
    with pytest.raises(ControllerConfigError, match=r"run 'c': camera\.noise_px differs from run"):
        run_configs(runs, lambda c: c)


def test_the_command_line_refuses_a_plan_with_per_run_options_or_realtime(tmp_path, capsys):
    plan = write(tmp_path, {"runs": [run_entry(tmp_path, "a")]})
    assert main(["controller", "--plan", str(plan), "--law", "rhc", "--no-rt"]) == 2
    assert "drop --law" in capsys.readouterr().err
    assert main(["controller", "--plan", str(plan), "--duration", "3", "--no-rt"]) == 2
    assert "drop --duration" in capsys.readouterr().err
    argv = ["controller", "--plan", str(plan), "--clock", "realtime", "--no-rt"]
    assert main(argv) == 2
    assert "lockstep only" in capsys.readouterr().err
    argv = ["controller", "--plan", str(plan), "--clock", "lockstep", "--profile", "cia402"]
    assert main([*argv, "--no-rt"]) == 2  # not a wait for a joint state that never comes
    assert "--plan runs on the dsp profile only" in capsys.readouterr().err
    # the first run runs on the processes as started: its seed must be theirs
    seeded = load_config(None).with_overrides({"controller.clock": "lockstep", "camera.seed": 3})
    plan = write(tmp_path, {"runs": [run_entry(tmp_path, "s3", seeded)]}, "seeded.json")
    assert main(["controller", "--plan", str(plan), "--no-rt"]) == 2
    err = capsys.readouterr().err
    assert "'s3' (the first) has camera.seed 3" in err and "has 0" in err
