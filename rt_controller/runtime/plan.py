"""``hil controller --plan FILE``: many lockstep runs on one set of rig processes.

Starting the three processes costs more than a 10 s lockstep run, so ``hil experiment`` hands
the controller a plan of runs. Between runs the controller resets the emulated DSP's scenario
on the simulator-control channel (:mod:`hal.sim_control`, zenoh ``hil/sim/control``:
simulation time 0, the initial state, a new session and camera noise seed, the vision process
restarting from that seed) and waits for the new session's DspStatus on CAN; each run's log
and summary are then those of ``hil up --config RUN.toml`` (tests compare them bit for bit).

The plan is JSON::

    {"runs": [{"name": "rhc-T0.1", "config": "configs/rhc-T0.1.toml", "law": "rhc",
               "duration_s": 10.0, "log": "logs/rhc-T0.1.mcap"}, ...]}

The runs may differ only in what the emulator and vision processes do not read (the
``controller``, ``rhc`` and ``gains`` sections, and a ``camera.seed`` the reset can carry).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hal.config import RigConfig, load_config
from hal.errors import HalError, HalStopped
from hal.secoc import rig_key
from hal.sim_control import SEED_MAX, SimControlSender
from rt_controller.config_rules import apply_overrides
from rt_controller.errors import ControllerConfigError, ControllerError

CONTROLLER_SECTIONS = ("controller", "rhc", "gains")
"""Sections only the controller reads: runs of one plan may differ in these alone."""
RESET_TIMEOUT_S = 5.0
"""How long the controller waits for the DSP to confirm a scenario reset."""


@dataclass(frozen=True)
class PlannedRun:
    """One run of a plan."""

    name: str
    config: Path
    log: Path
    duration_s: float
    law: str | None = None


def load_plan(path: str | Path) -> list[PlannedRun]:
    """The runs of the plan file; :class:`ControllerConfigError` naming what is wrong."""
    where = f"plan {path}"
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise ControllerConfigError(f"{where}: cannot read: {exc.strerror or exc}") from exc
    except json.JSONDecodeError as exc:
        raise ControllerConfigError(f"{where}: not JSON: {exc}") from exc
    runs = doc.get("runs") if isinstance(doc, dict) else None
    if not isinstance(runs, list) or not runs:
        raise ControllerConfigError(f'{where}: needs a non-empty list "runs"')
    out: list[PlannedRun] = []
    for i, item in enumerate(runs):
        out.append(_planned_run(item, f"{where}: run {i}"))
    names = [r.name for r in out]
    if len(set(names)) != len(names):
        raise ControllerConfigError(f"{where}: run names must be unique, got {names}")
    logs = [r.log.resolve() for r in out]
    if len(set(logs)) != len(logs):
        raise ControllerConfigError(f"{where}: two runs would write the same log")
    return out


def _planned_run(item: Any, where: str) -> PlannedRun:
    if not isinstance(item, dict):
        raise ControllerConfigError(f"{where}: must be an object")
    unknown = set(item) - {"name", "config", "log", "duration_s", "law"}
    if unknown:
        raise ControllerConfigError(f"{where}: unknown key(s) {sorted(unknown)}")
    for key in ("name", "config", "log"):
        if not isinstance(item.get(key), str) or not item[key]:
            raise ControllerConfigError(f"{where}: {key!r} must be a non-empty string")
    duration = item.get("duration_s")
    if (
        isinstance(duration, bool)
        or not isinstance(duration, int | float)
        or not (math.isfinite(duration) and duration > 0)
    ):
        raise ControllerConfigError(f"{where}: 'duration_s' must be a positive number")
    law = item.get("law")
    if law is not None and not isinstance(law, str):
        raise ControllerConfigError(f"{where}: 'law' must be a string")
    return PlannedRun(item["name"], Path(item["config"]), Path(item["log"]), float(duration), law)


def reset_seed(cfg: RigConfig) -> int | None:
    """The camera noise seed a scenario reset carries for a run of ``cfg`` (None when it does
    not fit :data:`~hal.sim_control.SEED_MAX`: such a seed is the processes' own, see
    :func:`world_of`)."""
    seed = cfg.camera.seed
    return seed if 0 <= seed <= SEED_MAX else None


def world_of(cfg: RigConfig) -> dict[str, Any]:
    """What the emulator and vision processes read of ``cfg`` and a plan cannot change from
    run to run: everything but the controller's sections and a camera seed that a scenario
    reset carries (:func:`reset_seed`)."""
    out = {k: v for k, v in cfg.to_dict().items() if k not in CONTROLLER_SECTIONS}
    if reset_seed(cfg) is not None:
        out["camera"] = {k: v for k, v in out["camera"].items() if k != "seed"}
    return out


def first_difference(a: dict[str, Any], b: dict[str, Any]) -> str | None:
    """The first ``section.key`` whose value differs between two config dicts, else None."""
    for section in sorted(set(a) | set(b)):
        sa, sb = a.get(section, {}), b.get(section, {})
        for key in sorted(set(sa) | set(sb)):
            if sa.get(key) != sb.get(key):
                return f"{section}.{key}"
    return None


def run_configs(
    runs: list[PlannedRun], prepare: Callable[[RigConfig], RigConfig]
) -> list[RigConfig]:
    """Each run's configuration (its file, its law, then ``prepare``: the command line's key
    and clock), checked to share the first run's world."""
    cfgs: list[RigConfig] = []
    for run in runs:
        cfg = prepare(apply_overrides(load_config(run.config), law=run.law))
        if cfgs:
            diff = first_difference(world_of(cfgs[0]), world_of(cfg))
            if diff is not None:
                raise ControllerConfigError(
                    f"plan run {run.name!r}: {diff} differs from run {runs[0].name!r}; the "
                    "emulator and vision processes were started with the first run's "
                    f"configuration (runs of one plan may differ in {CONTROLLER_SECTIONS} and "
                    f"camera.seed up to {SEED_MAX} only)"
                )
        cfgs.append(cfg)
    return cfgs


def check_started_seed(first: PlannedRun, cfg: RigConfig, started: RigConfig) -> None:
    """The plan's first run runs on the processes as they started (no reset before it): its
    camera seed must be theirs (``started``: the ``--config`` they were given); a clear
    :class:`ControllerConfigError` otherwise. Later runs name theirs in the reset."""
    if cfg.camera.seed != started.camera.seed:
        raise ControllerConfigError(
            f"plan run {first.name!r} (the first) has camera.seed {cfg.camera.seed}, but "
            f"--config, which the emulator and vision processes are started with, has "
            f"{started.camera.seed}: start the rig with the first run's configuration, or put "
            "a run of that seed first"
        )


def run_plan(
    runs: list[PlannedRun],
    cfgs: list[RigConfig],
    opts: Any,
    stop: threading.Event,
    emit: Callable[[dict[str, Any]], None],
) -> list[dict[str, Any]]:
    """Run the plan; ``emit`` gets each run's summary (with ``run`` and ``wall_s``) as soon as
    it ends. Stops early on ``stop``; raises :class:`ControllerError` when the DSP does not
    confirm a scenario reset (the runs so far were emitted)."""
    from rt_controller.runtime.daemon import ControllerDaemon, open_links

    out: list[dict[str, Any]] = []
    try:
        with open_links(cfgs[0], stop) as (dsp, session):
            sim = SimControlSender(session, key=rig_key(cfgs[0]))
            owed: tuple[int, ...] = ()
            for i, (run, cfg) in enumerate(zip(runs, cfgs, strict=True)):
                if stop.is_set():
                    break
                t0 = time.monotonic()
                if i:
                    try:
                        request = functools.partial(sim.reset_scenario, reset_seed(cfg))
                        dsp.await_new_session(RESET_TIMEOUT_S, request)
                    except HalError as exc:
                        raise ControllerError(f"plan run {run.name!r}: {exc}") from exc
                run_opts = dataclasses.replace(
                    opts, duration_s=run.duration_s, log_path=run.log, images_owed_before=owed
                )
                daemon = ControllerDaemon(cfg, run_opts, stop)
                summary = daemon.run((dsp, session))
                owed = daemon.images_owed  # images that may still come: not the next run's
                summary.update(run=run.name, wall_s=time.monotonic() - t0)
                out.append(summary)
                emit(summary)
    except HalStopped:  # told to stop while waiting for zenoh: no run started
        pass
    return out
