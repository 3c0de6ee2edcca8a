"""Start the rig's processes (emulator, vision, controller, optionally monitor), wait, stop them.

Used by ``hil up`` and ``hil experiment``. Every child runs ``python -m rt_controller.cli``; a
child that dies is reported with its exit status and the tail of its stderr, and nothing is
left running on any exit path:

* the children share one process group of their own (the first child leads it), so a stop can
  signal all of them, and anything they started, at once;
* each child asks the kernel for SIGTERM when its parent dies (``PR_SET_PDEATHSIG``, see
  :func:`follow_parent`), so even a SIGKILLed ``hil up`` leaves nothing running: the controller
  turns torque off and finishes its log, the DSP removes torque on its own;
* :func:`supervised` turns SIGTERM, SIGINT and SIGHUP to the supervisor into
  :class:`RigInterrupted`, so the children are stopped in order (controller first: torque off
  while the DSP still listens) before it exits.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from hal.config import load_config
from hal.zenoh_session import free_loopback_port
from rt_controller.errors import ControllerError
from rt_controller.rig.ending import ProcessEnd, dsp_report, log_path_said, summary_after
from rt_controller.rig.failures import (
    RigCancelled,
    RigHung,
    RigProcessDied,
    RigProcessError,
    with_tail,
)
from rt_controller.rig.kernel_cache import prepare_kernels
from rt_controller.rig.options import STARTUP_MARGIN_S, RigOptions, private_default_bus
from rt_controller.rig.supervise import (
    PARENT_ENV,
    RigInterrupted,
    kill_with_stacks,
    signals_deferred,
)
from rt_controller.runtime.counters import run_problems

STOP_TIMEOUT_S = 10.0
LOCKSTEP_MISSING_PERIOD_S = 0.5
"""Real time a lockstep DSP waits for a period's command before it counts the period missing
(``plant_emulator.dsp_lockstep.LOCKSTEP_REPLY_TIMEOUT_S``): its watchdog counts such periods."""
TRIP_MARGIN_S = 1.0
"""How much longer than its watchdog time the supervisor waits for a DSP's trip after the
controller died (a loaded host delays the emulator's loop)."""
WATCHDOG_TRIP_LINE = "hil emulator: fault: watchdog"
"""What the emulator prints on stderr when its watchdog trips (``plant_emulator.entry``)."""


@dataclass
class Child:
    name: str
    proc: subprocess.Popen
    stderr: IO[bytes]
    stdout: IO[bytes]

    def tail(self, lines: int = 15) -> str:
        self.stderr.flush()
        self.stderr.seek(0)
        text = self.stderr.read().decode(errors="replace").strip().splitlines()
        return "\n".join(text[-lines:])

    def output(self) -> str:
        self.stdout.flush()
        self.stdout.seek(0)
        return self.stdout.read().decode(errors="replace")


def group_running(pgid: int) -> bool:
    """Whether a process of group ``pgid`` still runs (zombies, which only wait to be reaped,
    do not count). Read from ``/proc``; elsewhere: whether the group can be signalled."""
    proc = Path("/proc")
    if not (proc / "self" / "stat").exists():
        try:
            os.killpg(pgid, 0)
        except (ProcessLookupError, PermissionError):
            return False
        return True
    for stat in proc.glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue  # it ended while we looked
        if int(fields[2]) == pgid and fields[0] not in ("Z", "X"):
            return True
    return False


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "rt_controller.cli", *args]


class Rig:
    """The three processes of one run; a context manager that always stops them."""

    def __init__(self, opts: RigOptions) -> None:
        self.opts = opts
        self.children: list[Child] = []
        self.endpoint = opts.zenoh_endpoint or f"tcp/127.0.0.1:{free_loopback_port()}"
        self.can = opts.can or private_default_bus(opts.config)
        self._key_dir: str | None = None
        self.key_file: Path | None = Path(opts.key_file) if opts.key_file else None
        """The rig key the children load (set by :meth:`start` when made fresh)."""

    def _ensure_key(self) -> Path:
        """The run's rig key: the given one (checked now), else a fresh one in a private
        directory (mode 0700, removed by :meth:`close`), so two rigs never share a key."""
        from hal.secoc import load_key_file, write_key_file

        if self.key_file is None:
            self._key_dir = tempfile.mkdtemp(prefix="hil-rig-key-")
            self.key_file = write_key_file(Path(self._key_dir) / "rig.key")
        else:
            load_key_file(self.key_file)
        return self.key_file

    def _common(self) -> list[str]:
        out = ["--zenoh-endpoint", self.endpoint, "--key-file", str(self._ensure_key())]
        if self.opts.config:
            out += ["--config", self.opts.config]
        return out

    def spawn(self, name: str, args: list[str]) -> Child:
        """Start ``args`` as the rig's child ``name``: in the rig's process group, its output
        kept for the summary, stopped and cleaned up with the rig (also a process started
        again after a fault)."""
        err = tempfile.TemporaryFile()  # noqa: SIM115 - closed by Rig.close()
        out = tempfile.TemporaryFile()  # noqa: SIM115 - closed by Rig.close()
        env = {**os.environ, "PYTHONUNBUFFERED": "1", PARENT_ENV: str(os.getpid())}
        group = self.children[0].proc.pid if self.children else 0
        proc = subprocess.Popen(
            args,
            stdout=out,
            stderr=err,
            stdin=subprocess.DEVNULL,
            env=env,
            process_group=group,
        )
        child = Child(name, proc, err, out)
        self.children.append(child)
        return child

    def start(self) -> None:
        o = self.opts
        # numba's compile on a cold cache is not part of the run or of its wall-clock budget
        prepare_kernels(o.config, o.law if o.plan is None else None, o.cancel)
        can = ["--can", self.can] if self.can else []
        # --json: the DSP's counters (its watchdog trips) on stdout when it stops
        emu = _cli("emulator", *can, *self._common(), "--json", *o.extra_emulator)
        if o.lockstep:
            emu.append("--lockstep")
        self.spawn("emulator", emu)
        # the emulator is the zenoh hub: on a slow host it may take a while to come up
        vision = _cli("vision", *self._common(), "--wait", f"{STARTUP_MARGIN_S:g}")
        self.spawn("vision", vision + o.extra_vision)
        if o.monitor:
            mon = _cli("monitor", *self._common())
            if o.monitor_host:
                mon += ["--host", o.monitor_host]
            if o.monitor_port is not None:
                mon += ["--port", str(o.monitor_port)]
            self.spawn("monitor", mon + o.extra_monitor)
        ctl = _cli("controller", *can, *self._common(), "--json")
        ctl += ["--clock", "lockstep" if o.lockstep else "realtime"]
        if o.plan is not None:
            ctl += ["--plan", str(o.plan)]
        else:
            ctl += ["--duration", f"{o.duration_s:g}"]
        if o.law and o.plan is None:
            ctl += ["--law", o.law]
        if o.log and o.plan is None:
            ctl += ["--log", str(o.log)]
        self.spawn("controller", ctl + o.extra_controller)

    def _check_alive(self, but: str) -> None:
        for c in self.children:
            if c.name not in (but, "monitor") and c.proc.poll() is not None:
                raise RigProcessDied(
                    ProcessEnd(c.name, c.proc.returncode, time.monotonic_ns()), c.tail()
                )

    def child(self, name: str) -> Child | None:
        return next((c for c in self.children if c.name == name), None)

    def wait_controller(self) -> dict[str, Any]:
        """Wait for the controller's run to end; its JSON summary. A controller that ended
        without one (killed, crashed) raises :class:`RigProcessDied`, as another process's
        death does."""
        ctl = self.wait_controller_exit()
        lines = self.summaries()
        # Status 1 with a summary: the run finished but is not clean (its "problems" say why).
        if ctl.proc.returncode not in (0, 1) or not lines:
            end = ProcessEnd("controller", ctl.proc.returncode, time.monotonic_ns())
            raise RigProcessDied(end, ctl.tail())
        return lines[-1]

    def finish_after(self, end: ProcessEnd) -> dict[str, Any]:
        """Stop the rig after ``end`` and the run's summary all the same
        (:func:`~rt_controller.rig.ending.summary_after`): the controller's, if it is still
        there to print it (it is stopped first), else its counters from the log; the DSP's
        watchdog account, waited for when the controller died; what the log holds."""
        if end.name == "controller":
            self._await_trip()
        codes = self.stop()
        lines = self.summaries()
        emulator, controller = self.child("emulator"), self.child("controller")
        dsp = dsp_report(emulator.output()) if emulator else {"reported": False}
        log = self.opts.log or (log_path_said(controller.tail(400)) if controller else None)
        o = self.opts
        base = self.what_runs(o.config, o.duration_s, o.law)
        out = summary_after(end, lines[-1] if lines else None, log, dsp, base)
        out["exit_codes"] = codes
        dead = self.child(end.name)
        out["stderr_tail"] = dead.tail(5) if dead else ""
        return out

    def what_runs(self, config: str | Path | None, duration_s: float, law: str | None) -> dict:
        """What this rig was asked to run (one run of ``duration_s`` on ``config``), for a
        summary the controller did not print."""
        cfg = load_config(config)
        rate = cfg.rates.control_hz
        return {
            "clock": "lockstep" if self.opts.lockstep else "realtime",
            "rate_hz": rate,
            "duration_s": duration_s,
            "law": law or cfg.controller.law,
            "can": self.can,
            "ticks": None,
            "planned_ticks": math.floor(duration_s * rate + 1e-9),
        }

    def summary_of_cut_run(self, end: ProcessEnd, index: int) -> dict[str, Any]:
        """Of a plan (stopped): the summary of its run ``index``, which ``end`` cut short: the
        controller's, if it printed one as it was stopped, else its log's."""
        from rt_controller.runtime.plan import load_plan

        assert self.opts.plan is not None
        run = load_plan(self.opts.plan)[index]
        lines = self.summaries()
        emulator = self.child("emulator")
        dsp = dsp_report(emulator.output()) if emulator else {"reported": False}
        base = {"run": run.name, **self.what_runs(run.config, run.duration_s, run.law)}
        partial = lines[index] if len(lines) > index else None
        out = summary_after(end, partial, run.log, dsp, base)
        dead = self.child(end.name)
        out["stderr_tail"] = dead.tail(5) if dead else ""
        return out

    def _await_trip(self) -> None:
        """After the controller died: wait (at most its watchdog time and
        :data:`TRIP_MARGIN_S`) until the emulator reports its watchdog's trip, so that the
        DSP's account is in the summary before the emulator is stopped. A DSP that was never
        armed does not trip: the wait then runs out."""
        emulator = self.child("emulator")
        if emulator is None or emulator.proc.poll() is not None:
            return
        cfg = load_config(self.opts.config)
        period = LOCKSTEP_MISSING_PERIOD_S if self.opts.lockstep else 1 / cfg.rates.control_hz
        deadline = time.monotonic() + cfg.dsp.watchdog_periods * period + TRIP_MARGIN_S
        while time.monotonic() < deadline and emulator.proc.poll() is None:
            if WATCHDOG_TRIP_LINE in emulator.tail(50):
                return
            time.sleep(0.02)

    def summaries(self) -> list[dict[str, Any]]:
        """Every JSON summary the controller printed so far (one per run of a plan)."""
        ctl = next(c for c in self.children if c.name == "controller")
        out = []
        for line in ctl.output().splitlines():
            if line.startswith("{"):
                with contextlib.suppress(json.JSONDecodeError):  # a line cut by a kill
                    out.append(json.loads(line))
        return out

    def wait_controller_exit(self) -> Child:
        """Wait until the controller exits (another child's death, the wall-clock budget and
        ``cancel`` end the wait with an exception); the controller's child."""
        ctl = next(c for c in self.children if c.name == "controller")
        budget = self.opts.wall_budget_s()
        deadline = time.monotonic() + budget
        while ctl.proc.poll() is None:
            if self.opts.cancel is not None and self.opts.cancel.is_set():
                raise RigCancelled("cancelled")
            self._check_alive(but="controller")
            if time.monotonic() > deadline:
                raise RigHung(
                    f"controller still running after its wall-clock budget of {budget:g} s "
                    "(--wall-timeout)"
                )
            time.sleep(0.05)
        return ctl

    def stop(self) -> dict[str, int | None]:
        """SIGTERM every child still running (controller first, so torque goes off while the
        DSP still listens), SIGKILL after a timeout, then anything left in their group."""
        codes: dict[str, int | None] = {}
        with signals_deferred():
            # the controller first and on its own; the others together (each stops alone)
            first = [c for c in self.children if c.name == "controller"]
            for group in (first, [c for c in self.children if c.name != "controller"]):
                running = [c for c in group if c.proc.poll() is None]
                for c in running:
                    c.proc.send_signal(signal.SIGTERM)
                for c in group:
                    if c in running:
                        try:
                            c.proc.wait(STOP_TIMEOUT_S)
                        except subprocess.TimeoutExpired:
                            kill_with_stacks(c.proc)
                    codes[c.name] = c.proc.returncode
            if self.children:
                group = self.children[0].proc.pid
                # what the children started (the controller's recorder finishing the log of a
                # killed controller) gets its time before the group is killed
                deadline = time.monotonic() + STOP_TIMEOUT_S
                while group_running(group) and time.monotonic() < deadline:
                    time.sleep(0.02)
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(group, signal.SIGKILL)
        return codes

    def close(self) -> None:
        try:
            self.stop()
        finally:
            for c in self.children:
                c.stderr.close()
                c.stdout.close()
            self.children.clear()
            if self._key_dir is not None:
                shutil.rmtree(self._key_dir, ignore_errors=True)
                self._key_dir = None

    def __enter__(self) -> Rig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def refused_to_start(end: ProcessEnd, summary: dict[str, Any]) -> bool:
    """Whether ``end`` is a process that refused to start: exit status 2 (the ``hil`` commands'
    bad-usage status: a CAN interface that does not exist, no vision process on the zenoh
    endpoint, ...) before the controller ran a tick. That is reported as an error (exit 2), not
    as a run that ended short."""
    return end.returncode == 2 and not summary.get("ticks")


def run_rig_plan(
    opts: RigOptions, runs: int
) -> tuple[list[dict[str, Any]], RigProcessError | None]:
    """:func:`run_rig` for a plan of ``runs`` lockstep runs (``opts.plan``): the summaries of
    the runs that ended, in order, and why the rest did not (None when all did). A run that
    is not clean has a summary with its problems; it does not stop the plan. Each summary's
    ``dsp`` holds the periods the DSP skipped in that run (``skipped_periods``).
    """
    if opts.plan is None or not opts.lockstep:
        raise ControllerError("run_rig_plan needs RigOptions.plan and lockstep")
    with Rig(opts) as rig:
        rig.start()
        error: RigProcessError | None = None
        try:
            ctl = rig.wait_controller_exit()
            if ctl.proc.returncode not in (0, 1):
                end = ProcessEnd("controller", ctl.proc.returncode, time.monotonic_ns())
                error = RigProcessDied(end, ctl.tail())
        except RigProcessError as exc:
            error = exc
        if isinstance(error, RigProcessDied) and error.end.name == "controller":
            rig._await_trip()
        summaries = rig.summaries()
        codes = rig.stop()
        if isinstance(error, RigProcessDied):  # the run it cut short gets its summary too
            cut = rig.summary_of_cut_run(error.end, len(summaries))
            if not refused_to_start(error.end, cut):
                summaries.append(cut)
        bad = [c for c in rig.children if c.name in ("emulator", "vision") and codes[c.name]]
        if bad and error is None:
            error = RigProcessError(
                "\n".join(
                    f"{c.name} exited with status {c.proc.returncode}:\n{c.tail()}" for c in bad
                )
            )
        if len(summaries) < runs and error is None:
            ctl = next(c for c in rig.children if c.name == "controller")
            error = RigProcessError(
                f"controller printed {len(summaries)} of {runs} summaries:\n{ctl.tail()}"
            )
        emulator = rig.child("emulator")
        by_run = (dsp_report(emulator.output()) if emulator else {}).get("skipped_by_run") or []
        for summary, skipped in zip(summaries, [*by_run, *[0] * len(summaries)], strict=False):
            summary["exit_codes"] = codes
            # a cut run's summary has the DSP's report already; skipped periods are this run's
            summary["dsp"] = {**summary.get("dsp", {}), "skipped_periods": skipped}
            had = summary.get("problems", [])
            summary["problems"] = [*had, *(p for p in run_problems(summary) if p not in had)]
        return summaries, error


def run_rig(opts: RigOptions) -> dict[str, Any]:
    """Start, wait for the controller's duration, stop; the controller's summary plus exits.

    Call it inside :func:`supervised` to turn SIGTERM/SIGINT/SIGHUP into an orderly stop.
    """
    with Rig(opts) as rig:
        rig.start()
        try:
            summary = rig.wait_controller()
            rig._check_alive(but="controller")  # one that died as the controller's run ended
        except RigProcessDied as exc:
            summary = rig.finish_after(exc.end)
            if refused_to_start(exc.end, summary):
                raise  # bad usage: the process's one line and exit 2, as for any command
            return summary
        except (RigInterrupted, RigHung) as exc:
            rig.stop()  # the controller first: it turns torque off and prints its summary
            lines = rig.summaries()
            exc.summary = lines[-1] if lines else None
            raise
        try:
            codes = rig.stop()
        except RigInterrupted as exc:  # a signal deferred while the rig stopped
            exc.summary = summary
            raise
        watch = {"controller", "monitor"}  # a failed live view is reported, never fatal
        for c in rig.children:  # a process that failed as it stopped: the run is not clean
            if c.name not in watch and codes.get(c.name) not in (0, None):
                end = ProcessEnd(c.name, c.proc.returncode, time.monotonic_ns())
                hung = end.returncode == -signal.SIGKILL  # its stderr ends in its stacks
                summary["problems"] = [
                    *summary.get("problems", []),
                    with_tail(f"{c.name} {end.how} when stopped", c.tail(40 if hung else 5)),
                ]
        emulator = rig.child("emulator")
        summary["dsp"] = dsp_report(emulator.output()) if emulator else {"reported": False}
        had = summary.get("problems", [])  # the controller's, without the DSP's report
        summary["problems"] = [*had, *(p for p in run_problems(summary) if p not in had)]
        summary["exit_codes"] = codes
        mon = next((c for c in rig.children if c.name == "monitor"), None)
        if mon is not None and codes.get("monitor") not in (0, None):
            how = ProcessEnd("monitor", mon.proc.returncode, time.monotonic_ns()).how
            summary["monitor_error"] = f"{how}: {mon.tail(3)}"
        return summary
