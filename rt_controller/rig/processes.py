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
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from hal.bus import isolated_spec, resolve_spec
from hal.config import load_config
from hal.zenoh_session import free_loopback_port
from rt_controller.errors import ControllerError
from rt_controller.rig.supervise import PARENT_ENV, RigInterrupted, signals_deferred

STOP_TIMEOUT_S = 10.0
STARTUP_MARGIN_S = 60.0
LOCKSTEP_SLOWEST = 20.0
"""A lockstep run is simulated time: ``hil up`` calls it hung only when it runs more than this
many times slower than real time (user-mode Linux runs about 10x slower than the host)."""


class RigProcessError(ControllerError, RuntimeError):
    """A rig process failed; the message carries its exit status and stderr tail."""


class RigHung(RigProcessError):
    """The controller was still running after its wall-clock budget; the rig was stopped.
    ``summary`` is what the controller reported when stopped (None if it reported nothing)."""

    summary: dict[str, Any] | None = None


def with_tail(message: str, tail: str) -> str:
    """``message``, then a child's stderr tail on the lines below when it has one."""
    return f"{message}:\n{tail}" if tail else message


class RigCancelled(ControllerError):
    """The run was cancelled (:attr:`RigOptions.cancel`) before it ended; its processes have
    been stopped."""


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


@dataclass
class RigOptions:
    """What to start."""

    config: str | None = None
    law: str | None = None
    duration_s: float = 10.0
    lockstep: bool = False
    can: str | None = None
    zenoh_endpoint: str | None = None
    log: Path | None = None
    key_file: Path | None = None
    """The rig key of every child; None: a fresh key for this run (private temporary dir)."""
    extra_controller: list[str] = field(default_factory=list)
    extra_vision: list[str] = field(default_factory=list)
    extra_emulator: list[str] = field(default_factory=list)
    wall_timeout_s: float | None = None
    """Wall-clock budget for the controller's run, start-up included; None: see
    :meth:`wall_budget_s`."""
    monitor: bool = False
    """Also start ``hil monitor`` (the live view); its failure never ends the run."""
    monitor_host: str | None = None
    monitor_port: int | None = None
    extra_monitor: list[str] = field(default_factory=list)
    plan: Path | None = None
    """A plan of lockstep runs for one controller (``hil controller --plan``, see
    :mod:`rt_controller.runtime.plan`): ``law`` and ``log`` are then unused and ``duration_s``
    is the plan's total simulated time (for the wall-clock budget)."""
    cancel: threading.Event | None = None
    """Set from another thread to stop this run (children stopped, :class:`RigCancelled`):
    ``hil experiment --jobs`` runs rigs in worker threads, and only the main thread gets
    signals."""

    def wall_budget_s(self) -> float:
        """How long :meth:`Rig.wait_controller` waits before calling the run hung: the given
        ``wall_timeout_s``, else the duration (realtime) or ``LOCKSTEP_SLOWEST`` times the
        simulated duration (lockstep), plus ``STARTUP_MARGIN_S`` for start-up."""
        if self.wall_timeout_s is not None:
            return self.wall_timeout_s
        scale = LOCKSTEP_SLOWEST if self.lockstep else 1.0
        return scale * self.duration_s + STARTUP_MARGIN_S


def private_default_bus(config: str | None) -> str | None:
    """The bus a rig uses when none is named: the configured/auto bus, except that the shared
    default ``udp_multicast`` group becomes a free port of its own, so that rigs started at the
    same time on one host (tests, experiments) never hear each other. A SocketCAN interface is a
    real shared bus and is kept as it is."""
    cfg = load_config(config)
    spec = resolve_spec(None if cfg.transport.can == "auto" else cfg.transport.can)
    if spec.interface == "udp_multicast" and spec.source == "auto":
        return isolated_spec("udp_multicast")
    return None


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

    def _start(self, name: str, args: list[str]) -> Child:
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
        can = ["--can", self.can] if self.can else []
        emu = _cli("emulator", *can, *self._common(), *o.extra_emulator)
        if o.lockstep:
            emu.append("--lockstep")
        self._start("emulator", emu)
        # the emulator is the zenoh hub: on a slow host it may take a while to come up
        vision = _cli("vision", *self._common(), "--wait", f"{STARTUP_MARGIN_S:g}")
        self._start("vision", vision + o.extra_vision)
        if o.monitor:
            mon = _cli("monitor", *self._common())
            if o.monitor_host:
                mon += ["--host", o.monitor_host]
            if o.monitor_port is not None:
                mon += ["--port", str(o.monitor_port)]
            self._start("monitor", mon + o.extra_monitor)
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
        self._start("controller", ctl + o.extra_controller)

    def _check_alive(self, but: str) -> None:
        for c in self.children:
            if c.name not in (but, "monitor") and c.proc.poll() is not None:
                raise RigProcessError(
                    f"{c.name} exited with status {c.proc.returncode}:\n{c.tail()}"
                )

    def wait_controller(self) -> dict[str, Any]:
        """Wait for the controller's run to end; its JSON summary."""
        ctl = self.wait_controller_exit()
        lines = self.summaries()
        # Status 1 with a summary: the run finished but is not clean (its "problems" say why).
        if ctl.proc.returncode not in (0, 1) or (ctl.proc.returncode == 1 and not lines):
            raise RigProcessError(
                with_tail(f"controller exited with status {ctl.proc.returncode}", ctl.tail())
            )
        if not lines:
            raise RigProcessError(with_tail("controller printed no summary", ctl.tail()))
        return lines[-1]

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
                            c.proc.kill()
                            c.proc.wait()
                    codes[c.name] = c.proc.returncode
            if self.children:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(self.children[0].proc.pid, signal.SIGKILL)
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


def run_rig_plan(
    opts: RigOptions, runs: int
) -> tuple[list[dict[str, Any]], RigProcessError | None]:
    """:func:`run_rig` for a plan of ``runs`` lockstep runs (``opts.plan``): the summaries of
    the runs that ended, in order, and why the rest did not (None when all did). A run that
    is not clean has a summary with its problems; it does not stop the plan.
    """
    if opts.plan is None or not opts.lockstep:
        raise ControllerError("run_rig_plan needs RigOptions.plan and lockstep")
    with Rig(opts) as rig:
        rig.start()
        error: RigProcessError | None = None
        try:
            ctl = rig.wait_controller_exit()
            if ctl.proc.returncode not in (0, 1):
                error = RigProcessError(
                    f"controller exited with status {ctl.proc.returncode}:\n{ctl.tail()}"
                )
        except RigProcessError as exc:
            error = exc
        summaries = rig.summaries()
        codes = rig.stop()
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
        for summary in summaries:
            summary["exit_codes"] = codes
        return summaries, error


def run_rig(opts: RigOptions) -> dict[str, Any]:
    """Start, wait for the controller's duration, stop; the controller's summary plus exits.

    Call it inside :func:`supervised` to turn SIGTERM/SIGINT/SIGHUP into an orderly stop.
    """
    with Rig(opts) as rig:
        rig.start()
        try:
            summary = rig.wait_controller()
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
        bad = {n: c for n, c in codes.items() if n not in watch and c not in (0, None)}
        if bad:
            tails = "\n".join(
                f"{c.name} exited with status {c.proc.returncode}:\n{c.tail()}"
                for c in rig.children
                if c.name in bad
            )
            raise RigProcessError(tails)
        summary["exit_codes"] = codes
        mon = next((c for c in rig.children if c.name == "monitor"), None)
        if mon is not None and codes.get("monitor") not in (0, None):
            summary["monitor_error"] = f"exited with status {codes['monitor']}: {mon.tail(3)}"
        return summary
