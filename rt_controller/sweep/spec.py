"""The study spec of ``hil sweep``: base config, axes, repetitions; expanded into run tasks.

A spec is one TOML file::

    [study]
    name = "robustness"        # optional, for the report
    engine = "simulate"        # simulate | rig (``--engine`` overrides)
    duration_s = 6.0           # simulated seconds per run
    repetitions = 8            # runs per point, each with its own camera noise seed
    timeout_s = 300.0          # wall-clock limit of one run (then recorded as failed)
    pass_f_final_px = 2.0      # report: a run passes when it ran clean and ends below this
    config = "rig.toml"        # optional base config file (relative to the spec)

    [base.camera]              # base config: sections as in a rig TOML, over ``config``
    noise_px = 0.5

    [[axes]]                   # a grid axis: the listed values
    key = "plant.z_wo"
    values = [0.8, 0.9, 1.0, 1.1, 1.2]

    [[axes]]                   # a distribution axis: `samples` draws in [low, high]
    key = "plant.theta1"
    distribution = "uniform"   # uniform | log-uniform | normal (mean, std; truncated)
    low = 0.8
    high = 1.2
    samples = 10

The points are the Cartesian product of the grid axes times the Monte Carlo draws: every
distribution axis is drawn ``samples`` times together (their ``samples`` must agree). Each
point runs ``repetitions`` times. Every run's config is built and validated here, by the
rules of every other command (:func:`rt_controller.config_rules.apply_overrides` for the keys
it knows, :meth:`hal.config.RigConfig.with_overrides` for the rest), so a bad spec is refused
with one line before anything runs.

Seeds and draws depend only on the spec: the spec hash (over the resolved base config, the
axes and the study settings, not the engine) seeds a :class:`numpy.random.SeedSequence`; a
run's camera seed comes from ``SeedSequence([hash, 0], spawn_key=(point, repetition))``, the
draws of axis ``i`` from ``SeedSequence([hash, 1], spawn_key=(i,))``. The run key (its content
hash: config, engine, duration) names the run in the results and for resuming.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hal.config import RigConfig, config_from_dict, image_noise_error, load_config, read_text_file
from hal.errors import HalConfigError
from rt_controller.config_rules import apply_overrides
from rt_controller.errors import ControllerConfigError

ENGINES = ("simulate", "rig")
DISTRIBUTIONS = ("uniform", "log-uniform", "normal")
MAX_RUNS = 1_000_000
SEED_LIMIT = 2**63 - 1
"""camera.seed's range is [0, 2^63 - 1]."""

APPLY_OVERRIDE_KEYS = {
    "controller.law": "law",
    "rates.control_hz": "rate",
    "rhc.horizon": "horizon",
    "rhc.steps": "steps",
    "rhc.kmax": "kmax",
    "rhc.zeta": "zeta",
    "scenario.disturbance": "disturbance",
}
"""Axis keys that go through :func:`apply_overrides`, so that a sweep over the horizon or the
rate follows the rules of ``--horizon`` and ``--rate`` (N from T, physics rate from rate)."""

_STUDY_KEYS = {
    "name": str,
    "engine": str,
    "duration_s": float,
    "repetitions": int,
    "timeout_s": float,
    "pass_f_final_px": float,
    "config": str,
}


class SweepSpecError(ControllerConfigError):
    """The study spec is invalid (one line naming the key)."""


@dataclass(frozen=True)
class Axis:
    """One axis: a grid (``values``) or a distribution (drawn ``samples`` times)."""

    key: str
    values: tuple[Any, ...] = ()
    distribution: str | None = None
    params: dict[str, float] = field(default_factory=dict)
    samples: int = 0

    @property
    def grid(self) -> bool:
        return self.distribution is None

    def as_dict(self) -> dict[str, Any]:
        if self.grid:
            return {"key": self.key, "values": list(self.values)}
        return {
            "key": self.key,
            "distribution": self.distribution,
            **self.params,
            "samples": self.samples,
        }


@dataclass(frozen=True)
class Study:
    name: str = "sweep"
    engine: str = "simulate"
    duration_s: float = 6.0
    repetitions: int = 1
    timeout_s: float = 600.0
    pass_f_final_px: float = 2.0
    config: str | None = None


@dataclass(frozen=True)
class RunTask:
    """One run: everything a worker needs (plain data, cheap to send)."""

    key: str
    """Content hash of the run (config, engine, duration): its name in the results."""
    point: int
    rep: int
    seed: int
    axes: dict[str, Any]
    """The point's axis values, by key."""
    config: dict[str, Any]
    """The run's validated config as a dict (:meth:`RigConfig.to_dict`)."""
    engine: str
    duration_s: float
    timeout_s: float
    spec_hash: str
    log_dir: str | None = None
    """Where the run keeps its log (``--keep-logs``); None: not kept."""


@dataclass
class Spec:
    """A parsed, validated spec and its expansion."""

    path: Path
    study: Study
    base: RigConfig
    axes: list[Axis]
    points: list[dict[str, Any]]
    spec_hash: str

    @property
    def axis_keys(self) -> list[str]:
        return [a.key for a in self.axes]

    def hardware_profiles(self) -> list[str]:
        """The hardware profiles (``hardware.profile``) the runs of the rig engine drive."""
        profiles = {
            point_config(self.base, v, p).hardware.profile for p, v in enumerate(self.points)
        }
        return sorted(profiles)

    @property
    def runs(self) -> int:
        return len(self.points) * self.study.repetitions

    def tasks(self, engine: str | None = None, log_dir: Path | None = None) -> list[RunTask]:
        """Every run, in (point, repetition) order, its config built and validated."""
        engine = engine or self.study.engine
        if engine not in ENGINES:
            raise SweepSpecError(f"engine must be {' or '.join(ENGINES)}, not {engine!r}")
        out = []
        for p, values in enumerate(self.points):
            cfg = point_config(self.base, values, p)
            if engine == "simulate" and cfg.hardware.profile != "dsp":
                raise SweepSpecError(
                    f"point {p}: hardware.profile = {cfg.hardware.profile!r} needs the rig "
                    "engine (--engine rig): the simulate engine runs the law in-process on "
                    "no hardware, so a profile would change nothing"
                )
            problem = image_noise_error(cfg) if engine == "rig" else None
            if problem is not None:  # the simulate engine's camera is the analytic one
                raise SweepSpecError(f"point {p} on the rig engine: {problem}")
            point_dict = cfg.to_dict()  # built and validated once per point, not per run
            for rep in range(self.study.repetitions):
                seed = run_seed(self.spec_hash, p, rep)  # in camera.seed's range by design
                run_cfg = {**point_dict, "camera": {**point_dict["camera"], "seed": seed}}
                key = run_key(run_cfg, engine, self.study.duration_s)
                out.append(
                    RunTask(
                        key=key,
                        point=p,
                        rep=rep,
                        seed=seed,
                        axes=values,
                        config=run_cfg,
                        engine=engine,
                        duration_s=self.study.duration_s,
                        timeout_s=self.study.timeout_s,
                        spec_hash=self.spec_hash,
                        log_dir=None if log_dir is None else str(log_dir),
                    )
                )
        return out


def _hash_int(spec_hash: str) -> int:
    return int(spec_hash[:32], 16)


def run_seed(spec_hash: str, point: int, rep: int) -> int:
    """The camera noise seed of run (point, rep): the spec, the point and the repetition only."""
    import numpy as np

    seq = np.random.SeedSequence([_hash_int(spec_hash), 0], spawn_key=(point, rep))
    return int(seq.generate_state(1, dtype=np.uint64)[0]) & SEED_LIMIT


def run_key(config: dict[str, Any], engine: str, duration_s: float) -> str:
    doc = {"config": config, "engine": engine, "duration_s": duration_s}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:20]


def point_config(base: RigConfig, values: dict[str, Any], point: int | None = None) -> RigConfig:
    """``base`` with a point's axis values, validated; errors name the axis and the value."""
    rule_kwargs = {APPLY_OVERRIDE_KEYS[k]: v for k, v in values.items() if k in APPLY_OVERRIDE_KEYS}
    plain = {k: v for k, v in values.items() if k not in APPLY_OVERRIDE_KEYS}
    try:
        cfg = base.with_overrides(plain) if plain else base
        return apply_overrides(cfg, **rule_kwargs) if rule_kwargs else cfg
    except (HalConfigError, ControllerConfigError) as exc:
        where = ", ".join(f"{k} = {v!r}" for k, v in values.items())
        at = f"point {point} " if point is not None else ""
        raise SweepSpecError(f"axes: {at}({where}): {_unkeyed(str(exc), values)}") from None


def _unkeyed(message: str, values: dict[str, Any]) -> str:
    """``message`` without a leading ``"KEY: "`` of an axis: the point already names it."""
    for key in values:
        if message.startswith(f"{key}: "):
            return message[len(key) + 2 :]
    return message


# ------------------------------------------------------------------------------------ parse
def _one(value: Any, typ: type, key: str) -> Any:
    if typ is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise SweepSpecError(f"{key}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise SweepSpecError(f"{key}: must be finite, got {value!r}")
        return float(value)
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise SweepSpecError(f"{key}: expected an integer, got {value!r}")
        return value
    if not isinstance(value, typ):
        raise SweepSpecError(f"{key}: expected a {typ.__name__}, got {value!r}")
    return value


def _study(data: Any) -> Study:
    if not isinstance(data, dict):
        raise SweepSpecError(f"[study]: expected a table, got {data!r}")
    kwargs = {}
    for key, value in data.items():
        if key not in _STUDY_KEYS:
            raise SweepSpecError(f"unknown key study.{key} (known keys: {', '.join(_STUDY_KEYS)})")
        kwargs[key] = _one(value, _STUDY_KEYS[key], f"study.{key}")
    study = Study(**kwargs)
    if study.engine not in ENGINES:
        raise SweepSpecError(f"study.engine: must be {' or '.join(ENGINES)}, not {study.engine!r}")
    if not 0 < study.duration_s <= 3600:
        raise SweepSpecError(f"study.duration_s: {study.duration_s!r} is out of range (0, 3600]")
    if not 1 <= study.repetitions <= 100_000:
        raise SweepSpecError(
            f"study.repetitions: {study.repetitions!r} is out of range [1, 100000]"
        )
    if not 0 < study.timeout_s <= 86_400:
        raise SweepSpecError(f"study.timeout_s: {study.timeout_s!r} is out of range (0, 86400]")
    if not study.pass_f_final_px > 0:
        raise SweepSpecError(
            f"study.pass_f_final_px: must be positive, got {study.pass_f_final_px}"
        )
    return study


_DIST_PARAMS = {
    "uniform": ("low", "high"),
    "log-uniform": ("low", "high"),
    "normal": ("mean", "std", "low", "high"),
}


def _plain(value: Any) -> bool:
    """A value a config key can take: a TOML number, string, boolean, or a list of them (not
    a date, a time or a table)."""
    if isinstance(value, list):
        return all(_plain(v) for v in value)
    return isinstance(value, bool | int | float | str)


def _canonical(value: Any) -> Any:
    """``value`` as the config sees it: a number as a float (``1`` and ``1.0`` are one point)."""
    if isinstance(value, list):
        return [_canonical(v) for v in value]
    if isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    return value


def _axis(i: int, data: Any) -> Axis:
    where = f"axes[{i}]"
    if not isinstance(data, dict):
        raise SweepSpecError(f"{where}: expected a table with key and values, got {data!r}")
    key = data.get("key")
    if not isinstance(key, str) or "." not in key:
        raise SweepSpecError(f'{where}.key: expected a config key like "plant.z_wo", got {key!r}')
    where = f"axis {key}"
    if key == "camera.seed":
        raise SweepSpecError(f"{where}: the repetitions set camera.seed (study.repetitions)")
    rest = {k: v for k, v in data.items() if k != "key"}
    if "values" in rest:
        if "distribution" in rest:
            raise SweepSpecError(f"{where}: give values (a grid) or a distribution, not both")
        extra = sorted(set(rest) - {"values"})
        if extra:
            raise SweepSpecError(f"{where}: unknown field(s) {', '.join(extra)} of a grid axis")
        values = rest["values"]
        if not isinstance(values, list) or not values:
            raise SweepSpecError(f"{where}.values: expected a non-empty list, got {values!r}")
        for value in values:
            if not _plain(value):
                raise SweepSpecError(
                    f"{where}.values: {value!r} is not a number, string, boolean or list of them"
                )
        if len({json.dumps(_canonical(v), sort_keys=True) for v in values}) != len(values):
            raise SweepSpecError(f"{where}.values: a value is listed twice: {values!r}")
        return Axis(key, tuple(values))
    dist = rest.get("distribution")
    if dist is None:
        raise SweepSpecError(f"{where}: needs values = [...] or a distribution")
    if dist not in DISTRIBUTIONS:
        raise SweepSpecError(
            f"{where}.distribution: must be {', '.join(DISTRIBUTIONS)}, not {dist!r}"
        )
    need = _DIST_PARAMS[dist]
    known = {"distribution", "samples", *need}
    extra = sorted(set(rest) - known)
    if extra:
        raise SweepSpecError(
            f"{where}: unknown field(s) {', '.join(extra)} of a {dist} axis "
            f"(it takes {', '.join(need)} and samples)"
        )
    missing = [p for p in need if p not in rest]
    if missing:
        raise SweepSpecError(
            f"{where}: a {dist} distribution needs {' and '.join(missing)} "
            f"(bounds low and high are required: every draw must be a valid setting)"
        )
    params = {p: _one(rest[p], float, f"{where}.{p}") for p in need}
    if not params["low"] < params["high"]:
        raise SweepSpecError(
            f"{where}: low must be below high, got {params['low']}, {params['high']}"
        )
    if dist == "log-uniform" and params["low"] <= 0:
        raise SweepSpecError(f"{where}.low: a log-uniform distribution needs low > 0")
    if dist == "normal" and not params["std"] > 0:
        raise SweepSpecError(f"{where}.std: must be positive, got {params['std']}")
    if "samples" not in rest:
        raise SweepSpecError(f"{where}: needs samples (the number of draws)")
    samples = _one(rest["samples"], int, f"{where}.samples")
    if not 1 <= samples <= MAX_RUNS:
        raise SweepSpecError(f"{where}.samples: {samples} is out of range [1, {MAX_RUNS}]")
    return Axis(key, (), dist, params, samples)


def _draw(axis: Axis, spec_hash: str, index: int) -> list[float]:
    import numpy as np

    rng = np.random.default_rng(
        np.random.SeedSequence([_hash_int(spec_hash), 1], spawn_key=(index,))
    )
    p, n = axis.params, axis.samples
    if axis.distribution == "uniform":
        return [float(v) for v in rng.uniform(p["low"], p["high"], n)]
    if axis.distribution == "log-uniform":
        return [float(v) for v in np.exp(rng.uniform(math.log(p["low"]), math.log(p["high"]), n))]
    out: list[float] = []  # normal, truncated to [low, high] by redrawing
    for _ in range(1000):
        v = rng.normal(p["mean"], p["std"], n)
        out += [float(x) for x in v if p["low"] <= x <= p["high"]]
        if len(out) >= n:
            return out[:n]
    raise SweepSpecError(
        f"axis {axis.key}: normal(mean {p['mean']}, std {p['std']}) rarely falls in "
        f"[{p['low']}, {p['high']}]"
    )


def spec_hash_of(study: Study, base: RigConfig, axes: list[Axis]) -> str:
    doc = {
        "study": {
            "duration_s": study.duration_s,
            "repetitions": study.repetitions,
            "timeout_s": study.timeout_s,
        },
        "base": base.to_dict(),
        "axes": [a.as_dict() for a in axes],
    }
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:20]


def load_spec(path: str | Path) -> Spec:
    """Read, validate and expand a spec; :class:`SweepSpecError` (one line) when it is bad."""
    p = Path(path)
    try:
        data = tomllib.loads(read_text_file(p, "spec"))
    except HalConfigError as exc:  # not a regular file, unreadable, not UTF-8: one line
        raise SweepSpecError(str(exc)) from None
    except (tomllib.TOMLDecodeError, RecursionError) as exc:
        raise SweepSpecError(f"{p}: not valid TOML: {' '.join(str(exc).split())}") from None
    try:
        return spec_from_dict(data, p)
    except (SweepSpecError, HalConfigError) as exc:
        raise SweepSpecError(f"{p}: {exc}") from None


def spec_from_dict(data: dict[str, Any], path: Path = Path("spec.toml")) -> Spec:
    unknown = sorted(set(data) - {"study", "base", "axes"})
    if unknown:
        raise SweepSpecError(
            f"unknown table(s) {', '.join(unknown)} (a spec has [study], [base], [[axes]])"
        )
    study = _study(data.get("study", {}))
    if study.config:
        cfg_path = Path(study.config)
        if not cfg_path.is_absolute():
            cfg_path = path.parent / cfg_path
        base_dict = load_config(cfg_path).to_dict()
    else:
        base_dict = RigConfig().to_dict()
    overlay = data.get("base", {})
    if not isinstance(overlay, dict):
        raise SweepSpecError(f"[base]: expected a table of config sections, got {overlay!r}")
    for section, body in overlay.items():
        if section not in base_dict:
            raise SweepSpecError(
                f"unknown section [base.{section}] (known sections: {', '.join(base_dict)})"
            )
        if not isinstance(body, dict):
            raise SweepSpecError(f"[base.{section}]: expected a table, got {body!r}")
        base_dict[section].update(body)
    try:
        base = config_from_dict(base_dict)
    except HalConfigError as exc:
        raise SweepSpecError(f"[base]: {exc}") from None
    raw_axes = data.get("axes", [])
    if not isinstance(raw_axes, list):
        raise SweepSpecError("axes: expected [[axes]] tables")
    axes = [_axis(i, a) for i, a in enumerate(raw_axes)]
    keys = [a.key for a in axes]
    dup = sorted({k for k in keys if keys.count(k) > 1})
    if dup:
        raise SweepSpecError(f"axes: {', '.join(dup)} given twice")
    draws = {a.samples for a in axes if not a.grid}
    if len(draws) > 1:
        raise SweepSpecError(
            f"axes: the distribution axes are drawn together and need one samples count, "
            f"got {sorted(draws)}"
        )
    grid_size = math.prod(len(a.values) for a in axes if a.grid)
    n_points = grid_size * (draws.pop() if draws else 1)
    if n_points * study.repetitions > MAX_RUNS:
        raise SweepSpecError(
            f"the study has {n_points * study.repetitions} runs, more than {MAX_RUNS}"
        )
    spec_hash = spec_hash_of(study, base, axes)
    drawn = {a.key: _draw(a, spec_hash, i) for i, a in enumerate(axes) if not a.grid}
    grid_axes = [a for a in axes if a.grid]
    points: list[dict[str, Any]] = []
    n_draws = len(next(iter(drawn.values()))) if drawn else 1
    for combo in itertools.product(*(a.values for a in grid_axes)):
        grid_values = dict(zip((a.key for a in grid_axes), combo, strict=True))
        for d in range(n_draws):
            values = {**grid_values, **{k: v[d] for k, v in drawn.items()}}
            points.append({k: values[k] for k in keys})
    spec = Spec(path, study, base, axes, points, spec_hash)
    for i, values in enumerate(points):  # every point's config valid before any run
        point_config(base, values, i)
    return spec
