"""Replay on the compile target the log was recorded with, or judge against the targets' spread.

The law's compiled code rounds by the CPU target numba compiled it for
(:mod:`rt_controller.compile_target`), so a log replays bit for bit only under the target it
was recorded with. :func:`replay_as_recorded` picks it:

* the log's target is this process's: the replay runs here;
* this host can run it (it has every feature the target enables): the replay runs in a new
  process whose numba compiles for it, in that target's own cache (the environment must be set
  before numba compiles anything, so not in this process);
* it cannot (or the log predates the record): the replay runs on this process's target. When
  that replay is not within tol, the log is replayed once more for a second target (``generic``,
  or this host's own when this process already runs ``generic``), and the largest difference
  between the two replays is the cross-target spread on this very log. A difference from the
  log up to :data:`SPREAD_FACTOR` times that spread counts as the compile target's (ok, with the
  figures); more is a change in the code, the settings or the inputs.

Two targets' replays of one log differ by 1.0e-5 to 1.3e-5 in tau (500 ticks of RHC;
znver4, skylake-avx512, generic; x86-64-v3 and haswell with znver4's features are exact),
the same order as the 2.9e-6 of the Zen 4 log on an Intel host; a changed gain or solver
setting moves tau by 1e-3 and more.

The new process is ``python -m rt_controller.logtools.target_replay REQUEST RESULT``: it
unpickles the request (log path and replay options) that this process wrote into a private
temporary folder, replays with :func:`~rt_controller.logtools.replay.replay_log` and pickles
the :class:`~rt_controller.logtools.replay.ReplayResult` (or the error's message) back.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hal.config import RigConfig
from rt_controller import compile_target as ct
from rt_controller.errors import ControllerError, LogError
from rt_controller.logtools.reader import LoadedLog
from rt_controller.logtools.replay import ReplayResult, abs_diff, replay_loaded, replay_log

SPREAD_FACTOR = 10.0
"""A difference from the log up to this many times the measured cross-target spread is the
compile target's (pairs of targets differ within a factor of 1.3 on the measured log; the
margin covers a pair of targets not available here)."""


def replay_as_recorded(
    log: LoadedLog,
    *,
    cfg_override: RigConfig | None = None,
    tol: float = 1e-9,
    out: Path | None = None,
    allow_partial: bool = False,
    say: Callable[[str], None] = lambda line: None,
) -> ReplayResult:
    """:func:`~rt_controller.logtools.replay.replay_loaded` on the log's compile target (see
    the module); ``say`` gets one line when the replay compiles for another target than this
    process's. The result's ``compile_target`` says which target ran and why."""
    options: dict[str, Any] = {
        "cfg_override": cfg_override,
        "tol": tol,
        "out": out,
        "allow_partial": allow_partial,
    }
    recorded, here = ct.recorded(log.run_info), ct.this_process()
    changed = ct.version_changes(log.run_info)
    libm, libm_missing = ct.libm_env(log.run_info)
    if recorded == here and ct.libm_matches(log.run_info):
        result = replay_loaded(log, **options)
        result.compile_target = f"compiled for {here.label()}, the log's target"
    elif recorded is not None and recorded.runnable():
        where = f"numba cache {ct.cache_dir(recorded)}"
        if libm:
            where += (
                f"; glibc's libm as on the log's host, {ct.ENV_TUNABLES}={libm[ct.ENV_TUNABLES]}"
            )
        line = f"compiling for the log's target {recorded.label()} in its own process ({where})"
        say(line)
        result = replay_in_process_for(recorded, log.path, options, libm)
        result.compile_target = line.replace("compiling", "compiled", 1)
    else:
        result = replay_loaded(log, **options)
        why = _why_not(recorded)
        result.compile_target = f"compiled for this process's {here.label()}: {why}"
        if not result.matches and result.ticks > 0:
            other = ct.host_native() if here.cpu_name == ct.GENERIC else ct.generic()
            say(
                f"{why}; replaying again for {other.label()} to measure the cross-target "
                "spread on this log"
            )
            twin = replay_in_process_for(other, log.path, {**options, "out": None})
            spread = max(
                float(abs_diff(result.u, twin.u).max(initial=0.0)),
                float(abs_diff(result.tau, twin.tau).max(initial=0.0)),
            )
            result.cross_target_spread = spread
            result.spread_limit = SPREAD_FACTOR * spread
            result.compile_target += (
                f"; cross-target spread {spread:.3g} ({here.label()} vs {other.label()} on "
                f"this log, x{SPREAD_FACTOR:g} allowed)"
            )
            if result.within_spread:
                result.notes.append(
                    f"not within tol {tol:g} but within the cross-target spread: "
                    f"{result.difference()}; up to {result.spread_limit:.3g} is the compile "
                    "target's difference"
                )
    if libm_missing and not result.matches:
        result.notes.append(
            f"the log's host ran glibc's libm variants for {', '.join(libm_missing)}, which "
            "this CPU lacks: sin, cos and exp may round differently in the last bit"
        )
    if changed and not result.matches:
        result.notes.append(
            "versions that change rounding differ from the recording: " + ", ".join(changed)
        )
    return result


def _why_not(recorded: ct.CompileTarget | None) -> str:
    """Why the log's own target is not used."""
    if recorded is None:
        return "the log does not record its compile target (recorded before hil.run had it)"
    missing = recorded.missing_here()
    if missing:
        more = f" and {len(missing) - 6} more" if len(missing) > 6 else ""
        shown = ", ".join(missing[:6]) + more
        return f"the log's target {recorded.label()} cannot run here (this CPU lacks {shown})"
    return f"the log's target {recorded.label()} ({recorded.triple}) is another architecture"


def rerun_on_log_target(
    path: str | Path, argv: list[str], say: Callable[[str], None]
) -> int | None:
    """Run ``hil ARGV`` compiled for the target the log ``path`` records (``hil --target-of``:
    the reruns of an experiment's or a sweep's runs). None when this process runs it: it
    already compiles for that target, or this host cannot run that target (a warning names the
    spread to expect). Otherwise the exit status of ``hil ARGV`` run in a new process whose
    environment, which the rig's processes inherit, compiles for the log's target."""
    from rt_controller.logtools.reader import read_hil_log

    info = read_hil_log(path, raw=False).run_info
    recorded, here = ct.recorded(info), ct.this_process()
    libm, _ = ct.libm_env(info)
    if recorded == here and ct.libm_matches(info):
        say(f"compiling for the target of {path}, {here.label()}, as this process does")
        return None
    if recorded is None or not recorded.runnable():
        say(
            f"warning: {_why_not(recorded)}; compiling for this host's {here.label()}: figures "
            "may differ from the log's by the cross-target spread (hil replay measures it)"
        )
        return None
    say(
        f"compiling for the target of {path}, {recorded.label()}, in new processes "
        f"(numba cache {ct.cache_dir(recorded)})"
    )
    cmd = [sys.executable, "-m", "rt_controller.cli", *argv]
    env = {**os.environ, **recorded.env(), **libm}
    return subprocess.run(cmd, env=env, stdin=None, check=False).returncode


def replay_in_process_for(
    target: ct.CompileTarget,
    path: Path,
    options: dict[str, Any],
    extra_env: dict[str, str] | None = None,
) -> ReplayResult:
    """:func:`replay_log` of ``path`` with ``options`` in a new process compiled for
    ``target`` (and ``extra_env``); :class:`LogError` with the child's reason when it fails."""
    env = {**os.environ, **target.env(), **(extra_env or {})}
    with tempfile.TemporaryDirectory(prefix="hil-replay-") as tmp:
        request, answer = Path(tmp, "request.pickle"), Path(tmp, "result.pickle")
        request.write_bytes(pickle.dumps((Path(path), options)))
        cmd = [sys.executable, "-m", __name__, str(request), str(answer)]
        proc = subprocess.run(cmd, env=env, stdin=subprocess.DEVNULL, check=False)
        if not answer.exists():
            raise LogError(f"the replay compiled for {target.label()} exited {proc.returncode}")
        kind, value = pickle.loads(answer.read_bytes())
    if kind == "error":
        raise LogError(value)
    return value


def _child(request: Path, answer: Path) -> int:
    """The new process's side of :func:`replay_in_process_for`."""
    path, options = pickle.loads(request.read_bytes())
    try:
        reply: tuple[str, Any] = ("result", replay_log(path, **options))
    except ControllerError as exc:
        reply = ("error", str(exc))
    answer.write_bytes(pickle.dumps(reply))
    return 0


if __name__ == "__main__":
    try:
        sys.exit(_child(Path(sys.argv[1]), Path(sys.argv[2])))
    except KeyboardInterrupt:  # Ctrl-C reached the parent too: it reports it
        sys.exit(130)
