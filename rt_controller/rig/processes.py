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
from rt_controller.rig.ending import (
    ProcessEnd,
    dsp_report,
    log_path_said,
    refused_to_start,
    stopped_from_outside,
    summary_after,
)
from rt_controller.rig.failures import (
    RigCancelled,
    RigHung,
    RigProcessDied,
    RigProcessError,
    with_tail,
)
from rt_controller.rig.kernel_cache import prepare_kernels
from rt_controller.rig.options import STARTUP_MARGIN_S, RigOptions, rig_bus
from rt_controller.rig.scratch import make_private_folder
from rt_controller.rig.supervise import (
    PARENT_ENV,
    RigInterrupted,
    group_running,
    kill_with_stacks,
    signals_deferred,
)
from rt_controller.runtime.counters import run_problems, run_warnings

STOP_TIMEOUT_S = 10.0
TRIP_MARGIN_S = 1.0
"""How much longer than its watchdog time the supervisor waits for a DSP's trip after the
controller died (a loaded host delays the emulator's loop)."""
STOPPED_IN_START_UP = "the controller was stopped before its first tick"
"""How a summary says a controller ended by the rig's SIGTERM in its start-up (it had no
handler yet): the supervisor's own stop, not a death."""
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


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "rt_controller.cli", *args]


class Rig:
    """The three processes of one run; a context manager that always stops them."""

    def __init__(self, opts: RigOptions) -> None:
        self.opts = opts
        self.children: list[Child] = []
        self.endpoint = opts.zenoh_endpoint or f"tcp/127.0.0.1:{free_loopback_port()}"
        self.can = rig_bus(opts)
        self._key_dir: Path | None = None
        self.key_file: Path | None = Path(opts.key_file) if opts.key_file else None
        """The rig key the children load (set by :meth:`start` when made fresh)."""

    def _ensure_key(self) -> Path:
        """The run's rig key: the given one (checked now), else a fresh one in a private folder
        (:mod:`~rt_controller.rig.scratch`, removed by :meth:`close`): rigs never share a key."""
        from hal.secoc import load_key_file, write_key_file

        if self.key_file is None:
            self._key_dir = make_private_folder("hil-rig-key-")
            self.key_file = write_key_file(self._key_dir / "rig.key")
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
        # a stop signal out of Popen after the fork would orphan the child: held till it is ours
        with signals_deferred():
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
            ctl += ["--log", str(o.log), *(["--force"] if o.replace_log else [])]
        self.spawn("controller", ctl + o.extra_controller)

    def _check_alive(self, but: str) -> None:
        for c in self.children:
            if c.name not in (but, "monitor") and c.proc.poll() is not None:
                end = ProcessEnd(c.name, c.proc.returncode, time.monotonic_ns(), unasked=True)
                raise RigProcessDied(end, c.tail())

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
        watchdog account, waited for when the controller died; what the log holds. A stop
        signal meanwhile waits until the summary is made (:class:`RigInterrupted` carries it)."""
        out = None
        try:
            with signals_deferred():
                if end.name == "controller":
                    self._await_trip()
                out = self._summary_after(end, self.stop())
        except RigInterrupted as exc:
            exc.summary = out
            raise
        return out

    def finish_hung(self, at_ns: int) -> dict[str, Any]:
        """After the wall-clock budget ran out (at ``at_ns``): stop the rig (a controller that
        does not stop is killed, its stacks in the problem) and the run's summary from what
        is left, as after a death."""
        codes, ctl = self.stop(), self.child("controller")
        why = f"its wall-clock budget of {self.opts.wall_budget_s():g} s ran out"
        end = ProcessEnd("controller", codes.get("controller") or 0, at_ns, stopped_because=why)
        out = self._summary_after(end, codes)
        if ctl is not None and end.returncode == -signal.SIGKILL:
            out["problems"].append(with_tail(f"controller {end.how} when stopped", ctl.tail(40)))
        return out

    def finish_interrupted(self, interrupt: RigInterrupted) -> dict[str, Any]:
        """After a stop signal to the supervisor: stop the rig; the controller's summary of
        the run so far (stopped by the signal the supervisor got, not the SIGTERM it passed
        on) with the DSP's account, else (it was still starting) what is left, as after a
        death."""
        at_ns, why = time.monotonic_ns(), str(interrupt)
        codes = self.stop()
        lines = self.summaries()
        if lines:
            emulator = self.child("emulator")
            dsp = dsp_report(emulator.output()) if emulator else {"reported": False}
            out = {**lines[-1], "dsp": dsp, "exit_codes": codes}
            if out.get("end_reason") == "stopped":
                out["stop_signal"] = signal.Signals(interrupt.signum).name
                out["warnings"] = run_warnings(out)  # "stopped by SIGINT" in them too
            return out
        if self.child("controller") is None:  # stopped while the rig was being started
            o = self.opts
            base = self.what_runs(o.config, o.duration_s, o.law)
            return {
                **base,
                "end_reason": f"{why} before the controller started",
                "exit_codes": codes,
            }
        out = self._summary_after(
            ProcessEnd("controller", codes.get("controller") or 0, at_ns), codes
        )
        if codes.get("controller") == -signal.SIGTERM:  # ended by the rig's stop, in start-up
            said, out["end_reason"] = out["end_reason"], f"{why}: {STOPPED_IN_START_UP}"
            out["problems"] = [p.replace(said, out["end_reason"]) for p in out["problems"]]
        return out

    def _summary_after(self, end: ProcessEnd, codes: dict[str, int | None]) -> dict[str, Any]:
        """The summary after ``end`` on the stopped rig (its exit ``codes``)."""
        lines, ctl, o = self.summaries(), self.child("controller"), self.opts
        log = o.log or (log_path_said(ctl.tail(400)) if ctl else None)
        base = self.what_runs(o.config, o.duration_s, o.law)
        return {**self._after(end, lines[-1] if lines else None, log, base), "exit_codes": codes}

    def _after(self, end: ProcessEnd, partial: dict | None, log: Path | None, base: dict) -> dict:
        """:func:`summary_after` with the DSP's report and the dead process's last words."""
        emulator, dead, ctl = self.child("emulator"), self.child(end.name), self.child("controller")
        dsp = dsp_report(emulator.output()) if emulator else {"reported": False}
        out = summary_after(end, partial, log, dsp, base, ctl.proc.pid if ctl else None)
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
        base = {"run": run.name, **self.what_runs(run.config, run.duration_s, run.law)}
        return self._after(end, lines[index] if len(lines) > index else None, run.log, base)

    def _await_trip(self) -> None:
        """After the controller died: wait (at most its watchdog time and
        :data:`TRIP_MARGIN_S`) until the emulator reports its watchdog's trip, so that the
        DSP's account is in the summary before the emulator is stopped. A DSP that was never
        armed does not trip: the wait then runs out."""
        emulator = self.child("emulator")
        if emulator is None or emulator.proc.poll() is not None:
            return
        cfg = load_config(self.opts.config)
        # a lockstep DSP counts a period missing after dsp.lockstep_reply_timeout_s of real time
        lockstep_period = cfg.dsp.lockstep_reply_timeout_s
        period = lockstep_period if self.opts.lockstep else 1 / cfg.rates.control_hz
        deadline = time.monotonic() + cfg.dsp.watchdog_periods * period + TRIP_MARGIN_S
        while time.monotonic() < deadline and emulator.proc.poll() is None:
            if WATCHDOG_TRIP_LINE in emulator.tail(50):
                return
            time.sleep(0.02)

    def summaries(self) -> list[dict[str, Any]]:
        """Every JSON summary the controller printed so far (one per run of a plan)."""
        ctl = self.child("controller")
        out: list[dict[str, Any]] = []
        for line in ctl.output().splitlines() if ctl else ():
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
            if self._key_dir is not None:  # (a second close finds it gone: no error)
                shutil.rmtree(self._key_dir, ignore_errors=True)

    def __enter__(self) -> Rig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


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
        except RigCancelled as exc:  # the runs that ended before keep their summaries
            exc.summaries = rig.summaries()
            raise
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
            if summary.get("end_reason") == "stopped":  # the plan's runs end on their own
                had = [*had, stopped_from_outside(summary)]
            summary["problems"] = [*had, *(p for p in run_problems(summary) if p not in had)]
        return summaries, error


def run_rig(opts: RigOptions) -> dict[str, Any]:
    """Start, wait for the controller's duration, stop; the controller's summary plus exits.

    Call it inside :func:`supervised` to turn SIGTERM/SIGINT/SIGHUP into an orderly stop.
    """
    with Rig(opts) as rig:
        try:
            rig.start()
            summary = rig.wait_controller()
            rig._check_alive(but="controller")  # one that died as the controller's run ended
        except RigProcessDied as exc:
            summary = rig.finish_after(exc.end)
            if refused_to_start(exc.end, summary):
                raise  # bad usage: the process's one line and exit 2, as for any command
            return summary
        except RigHung as exc:
            exc.summary = rig.finish_hung(time.monotonic_ns())
            raise
        except RigInterrupted as exc:  # the controller is stopped first and says its summary
            with signals_deferred(deliver=False):  # a second Ctrl-C asks for nothing more
                exc.summary = rig.finish_interrupted(exc)
            raise
        if summary.get("end_reason") == "stopped":  # by a stop signal this rig did not send
            summary["problems"] = [*summary.get("problems", []), stopped_from_outside(summary)]
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
