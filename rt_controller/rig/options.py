"""What a rig run is asked to do (:class:`RigOptions`), its wall-clock budget, and the private
default bus of rigs that run side by side."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from pathlib import Path

from hal.bus import BusSpec, isolated_spec, resolve_spec
from hal.config import load_config
from hal.errors import HalConfigError

STARTUP_MARGIN_S = 60.0
LOCKSTEP_SLOWEST = 20.0
"""A lockstep run is simulated time: ``hil up`` calls it hung only when it runs more than this
many times slower than real time (user-mode Linux runs about 10x slower than the host)."""


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
    replace_log: bool = True
    """Replace an existing ``log`` (``hil up`` without ``--force``: refuse it)."""
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


def rig_bus(opts: RigOptions) -> str | None:
    """The bus of the rig's children (a rig of :func:`local_rig`): ``opts.can``, else
    :func:`private_default_bus`."""
    local_rig(opts.config)
    return opts.can or private_default_bus(opts.config)


def local_rig(config: str | Path | None) -> None:
    """A rig's processes run on this host and meet over loopback: a configuration whose zenoh
    transport is a file (``transport.zenoh_config``: processes on several hosts) is refused in
    one line, before anything starts (each child would take the file, and the second to listen
    fails)."""
    if load_config(config).transport.zenoh_config:
        raise HalConfigError(
            "transport.zenoh_config: a rig started by one command runs on this host over "
            "loopback; with a zenoh config file, start hil emulator, hil vision and hil "
            "controller by hand on their hosts (docs/tutorials/two-hosts.md)"
        )


def emulator_bus_warning(spec: BusSpec) -> str | None:
    """What to say when a rig (which always starts the emulated DSP) is given a bus that may
    hold hardware: a vendor adapter or a SocketCAN interface other than ``vcan*``. None for
    the host-local buses (udp_multicast, python-can's virtual, vcan)."""
    channel = str(spec.channel or "")
    if spec.interface in ("udp_multicast", "virtual") or (
        spec.interface == "socketcan" and channel.startswith("vcan")
    ):
        return None
    return (
        f"{spec} may be a bus with hardware on it: the rig starts its emulated DSP there, "
        "so with a real DSP on it there would be two DSPs (docs/tutorials/real-can.md)"
    )


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
