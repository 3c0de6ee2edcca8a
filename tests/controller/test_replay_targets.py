"""A log replays bit for bit whatever numba compile target the replaying process has.

The slow tests record an RHC log in a process compiled for one target and replay it with
``hil replay --tol 1e-9`` from processes compiled for native, generic, znver4 and
skylake-avx512 (each selected with ``NUMBA_CPU_NAME``, as a user would); and they judge a log
whose target this host cannot run against the cross-target spread. Every target keeps its own
numba cache (``compile_target.cache_dir``), so only the first run of each target compiles.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hal.config import RigConfig
from rt_controller import compile_target as ct
from rt_controller.runtime.recorder import default_run_info

ROOT = Path(__file__).resolve().parents[2]
TICKS = 200
"""4 s at 50 Hz: past the target jump at 3 s, where targets' roundings part the most."""
RECORD = """
import sys
from pathlib import Path
from hal.config import RigConfig
from tests.controller.test_replay import record_run
cfg = RigConfig().with_overrides({"controller.law": "rhc"})
record_run(Path(sys.argv[1]), cfg, int(sys.argv[2]))
"""
REPLAY_TARGETS = ["native", "generic", "znver4", "skylake-avx512"]
AMX = ("amx-tile", "amx-int8", "amx-bf16")


def rounds_apart_from_generic() -> bool:
    """Whether a target with this host's features and ``generic`` must round apart in the RHC
    loop, from a fact of the CPU alone (not from the code under test): with FMA here, fastmath
    ``contract`` fuses multiply-adds in the one and cannot in the other (tests/support/
    tolerances.py measured every FMA build apart from generic). Without FMA they may round
    alike, and a test that needs a spread between them can only skip."""
    return "fma" in ct.host_features()


def env_for(name: str) -> dict[str, str]:
    """The environment of a process compiled for ``name`` (``native``: none set), with the
    host's features as numba takes them when only the name is set, in that target's cache."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_CPU_")}
    if name == "native":
        target = ct.host_native()
    else:
        features = "" if name == ct.GENERIC else ct.host_feature_string()
        target = ct.CompileTarget(name, features)
        env[ct.ENV_NAME] = name
    env[ct.ENV_CACHE] = str(ct.cache_dir(target))
    return env


def record(path: Path, target: ct.CompileTarget, **extra_env: str) -> Path:
    """An RHC log recorded in a process compiled for ``target`` (with ``extra_env``)."""
    env = {**os.environ, **target.env(), **extra_env}
    cmd = [sys.executable, "-c", RECORD, str(path), str(TICKS)]
    subprocess.run(cmd, env=env, cwd=ROOT, check=True, timeout=900)
    return path


def hil(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    """``hil ARGS`` in a new process with ``env``, its output captured."""
    cmd = [sys.executable, "-m", "rt_controller.cli", *args]
    return subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, timeout=900)


def hil_replay(log: Path, env: dict[str, str], *extra: str) -> tuple[int, dict, str]:
    """``hil replay LOG --tol 1e-9 --json`` in a new process: exit code, JSON, stderr."""
    proc = hil(env, "replay", str(log), "--tol", "1e-9", "--json", *extra)
    return proc.returncode, json.loads(proc.stdout or "null"), proc.stderr


# ------------------------------------------------------------------------------ the record


def test_the_run_info_records_this_process_target_and_versions():
    info = default_run_info(RigConfig(), 0, 0)
    target = ct.recorded(info)
    assert target == ct.this_process()
    assert target.triple
    # a real CPU's features; the portable target (NUMBA_CPU_NAME=generic) names none
    assert target.enabled or target.cpu_name == "generic"
    for key in ct.VERSION_KEYS:
        assert info[key] and info[key] != "unknown", key
    assert ct.version_changes(info) == []


def test_a_log_from_before_the_record_has_no_target():
    assert ct.recorded({"law": "rhc", "numpy_version": "2.0.0"}) is None


def test_changed_versions_are_named():
    info = {**ct.versions(), "numba_version": "0.1.0", "glibc_version": "2.17"}
    changes = ct.version_changes(info)
    assert [c.split()[0] for c in changes] == ["numba", "glibc"]
    assert changes[0].startswith("numba 0.1.0 -> ")


def test_a_target_with_a_feature_this_cpu_lacks_cannot_run_here():
    host = ct.host_native()
    assert host.runnable() and host.missing_here() == []
    alien = ct.CompileTarget("fantasy", host.features + ",+no-such-feature", host.triple)
    assert not alien.runnable()
    assert alien.missing_here() == ["no-such-feature"]
    assert not ct.CompileTarget(
        host.cpu_name, host.features, "aarch64-unknown-linux-gnu"
    ).runnable()
    assert ct.generic().runnable()


def test_each_target_compiles_into_its_own_cache():
    host, gen = ct.host_native(), ct.generic()
    assert ct.cache_dir(host) != ct.cache_dir(gen)
    same_name = ct.CompileTarget(host.cpu_name, host.features + ",+no-such-feature")
    assert ct.cache_dir(same_name) != ct.cache_dir(host)
    env = gen.env()
    assert env == {
        "NUMBA_CPU_NAME": "generic",
        "NUMBA_CPU_FEATURES": "",
        "NUMBA_CACHE_DIR": str(ct.cache_dir(gen)),
    }


def test_libm_is_narrowed_to_what_the_log_host_had(monkeypatch):
    monkeypatch.delenv("GLIBC_TUNABLES", raising=False)
    mine = ct.libm_features()
    assert ct.libm_matches({ct.KEY_LIBM: ",".join(sorted(mine))})
    assert ct.libm_env({ct.KEY_LIBM: ",".join(sorted(mine))}) == ({}, [])
    assert ct.libm_env({}) == ({}, []) and ct.libm_matches({})  # a log from before the record
    env, missing = ct.libm_env({ct.KEY_LIBM: ""})  # a host without FMA, AVX2 or AVX
    if mine:
        names = sorted(ct.LIBM_FEATURES[f] for f in mine)
        off = env["GLIBC_TUNABLES"].removeprefix("glibc.cpu.hwcaps=").split(",")
        assert sorted(v.removeprefix("-") for v in off) == names
        assert not ct.libm_matches({ct.KEY_LIBM: ""})
    assert missing == []
    assert ct.libm_env({ct.KEY_LIBM: "fma,no-such-feature"})[1] == ["no-such-feature"]
    monkeypatch.setenv("GLIBC_TUNABLES", "glibc.malloc.check=0:glibc.cpu.hwcaps=-FMA,-AVX2")
    assert not {"fma", "avx2"} & ct.libm_features()


# --------------------------------------------------------------------------- exact replay


@pytest.fixture(scope="module")
def skylake_log(tmp_path_factory) -> Path:
    target = ct.CompileTarget("skylake-avx512", ct.host_feature_string())
    return record(tmp_path_factory.mktemp("skylake") / "rhc.mcap", target)


@pytest.mark.slow
@pytest.mark.timeout(1800)
@pytest.mark.parametrize("replay_target", REPLAY_TARGETS)
def test_a_log_replays_exactly_under_each_target(skylake_log, replay_target):
    code, out, err = hil_replay(skylake_log, env_for(replay_target))
    assert code == 0, err
    assert out["matches"] and out["max_abs_dtau"] == 0.0 and out["max_abs_du"] == 0.0
    assert "skylake-avx512" in out["compile_target"]
    if replay_target != "skylake-avx512":  # another target than the log's: said in one line
        assert "compiling for the log's target skylake-avx512" in err


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_a_log_from_a_host_without_fma_replays_exactly(tmp_path):
    if not {"fma", "avx2"} <= ct.libm_features():
        pytest.skip("this host's libm has no FMA variants to turn off")
    target = ct.CompileTarget("skylake-avx512", ct.host_feature_string())
    no_fma = "glibc.cpu.hwcaps=-AVX2,-FMA,-AVX"  # an older rig PC's libm
    record(tmp_path / "rhc.mcap", target, GLIBC_TUNABLES=no_fma)
    code, out, err = hil_replay(tmp_path / "rhc.mcap", env_for("generic"))
    assert code == 0, err
    assert out["max_abs_dtau"] == 0.0 and out["max_abs_du"] == 0.0
    assert "GLIBC_TUNABLES=glibc.cpu.hwcaps=" in out["compile_target"]


# ------------------------------------------------------------- a target this host cannot run


@pytest.fixture(scope="module")
def amx_log(tmp_path_factory) -> Path:
    """A log compiled for a Sapphire Rapids with AMX (no AMX instruction is ever emitted for
    the law, so it runs here; but this host cannot run that target's code in general)."""
    if not set(AMX) - ct.host_features():
        pytest.skip("this host has AMX: it can run every target the test could record")
    features = ct.host_feature_string()
    for name in AMX:
        features = features.replace(f"-{name},", f"+{name},")
    target = ct.CompileTarget("sapphirerapids", features)
    return record(tmp_path_factory.mktemp("amx") / "rhc.mcap", target)


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_a_target_this_host_cannot_run_is_judged_against_the_measured_spread(amx_log):
    code, out, err = hil_replay(amx_log, env_for("generic"))
    assert "cannot run here (this CPU lacks amx-" in out["compile_target"]
    if out["matches"] and not rounds_apart_from_generic():
        pytest.skip("no FMA here: generic and sapphirerapids round alike, no spread to judge")
    assert not out["matches"], "the log's target and generic must round apart on an FMA host"
    assert code == 0, err
    assert out["within_spread"] and out["ok"]
    spread = out["cross_target_spread"]
    assert 0 < out["max_abs_dtau"] <= 10 * spread
    assert "cross-target spread" in out["compile_target"]
    assert any("within the cross-target spread" in note for note in out["notes"])


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_a_changed_gain_is_more_than_the_spread_and_says_so(amx_log):
    code, out, err = hil_replay(amx_log, env_for("generic"), "--set", "gains.kp=0.3")
    assert code == 1
    assert not out["ok"] and not out["within_spread"]
    line = err.strip().splitlines()[-1]
    assert line.startswith("hil replay: replay differs from the log: max |dtau| = ")
    assert "more than the cross-target spread explains" in line


# ------------------------------------------------------------------ reruns: hil --target-of


def test_target_of_is_taken_out_of_the_rerun_command_line():
    from rt_controller.cli import without_option

    argv = ["--target-of", "a.mcap", "up", "--lockstep", "--target-of=b.mcap", "--law", "rhc"]
    assert without_option(argv, "--target-of") == ["up", "--lockstep", "--law", "rhc"]


def simulate_j(env: dict[str, str], *front: str) -> tuple[float, str]:
    """J of a 4 s ``hil simulate --law rhc`` (the target jump at 3 s): J and stderr."""
    proc = hil(env, *front, "simulate", "--law", "rhc", "--duration", "4", "--json", "-q")
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)["J"], proc.stderr


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_a_rerun_with_target_of_compiles_for_the_logged_target(skylake_log):
    logged, _ = simulate_j(env_for("skylake-avx512"))
    rerun, err = simulate_j(env_for("generic"), "--target-of", str(skylake_log))
    assert rerun == logged  # bit for bit: J is a float64 in JSON
    assert "compiling for the target of" in err and "skylake-avx512" in err


# ------------------------------------------------------- sweeps: resumed on the first target

ONE_POINT = (
    '[study]\nduration_s = 4.0\n[base.controller]\nlaw = "rhc"\n'
    '[[axes]]\nkey = "plant.z_wo"\nvalues = [1.2]\n'
)


def sweep_j(spec: Path, out: Path, env: dict[str, str]) -> tuple[float, str]:
    """J of the one run of ``spec`` swept into ``out`` (simulate engine, one worker)."""
    args = ("--workers", "1", "--engine", "simulate", "--json")
    proc = hil(env, "sweep", str(spec), "--out", str(out), *args)
    assert proc.returncode == 0, proc.stderr
    rows = [json.loads(line) for line in (out / "rows.jsonl").read_text().splitlines()]
    return rows[-1]["J"], proc.stderr


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_a_resumed_sweep_compiles_for_its_first_rows_target(tmp_path):
    pytest.importorskip("distributed")
    spec = tmp_path / "one.toml"
    spec.write_text(ONE_POINT)
    first, _ = sweep_j(spec, tmp_path / "sky", env_for("skylake-avx512"))
    kept = json.loads((tmp_path / "sky" / "compile_target.json").read_text())
    assert kept["cpu_name"] == "skylake-avx512"
    # this host resumes it with a portable (generic) build, whose rows would round apart
    here, _ = sweep_j(spec, tmp_path / "generic", env_for("generic"))
    if here == first and not rounds_apart_from_generic():
        pytest.skip("no FMA here: skylake-avx512 and generic round alike, nothing to tell apart")
    assert here != first, "skylake-avx512 and generic must round apart on an FMA host"
    # the sweep's first rows came from a skylake-avx512 host; this host resumes it
    resumed = tmp_path / "resumed"
    resumed.mkdir()
    (resumed / "compile_target.json").write_text(json.dumps(kept))
    again, err = sweep_j(spec, resumed, env_for("generic"))
    assert again == first
    assert "workers compile for the sweep's target skylake-avx512" in err
