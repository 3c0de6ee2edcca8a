"""What the master hears from each drive, from canopen's receive thread: the TPDOs of every
SYNC, the heartbeats (boot-up, NMT state, loss) and the EMCYs. EMCYs and a lost heartbeat are
faults: recorded (the last :data:`EVENTS_KEPT`) and counted by label, as the DSP's are."""

from __future__ import annotations

import threading
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field

import canopen
from canopen.emcy import EmcyError
from canopen.nmt import NMT_STATES
from canopen.profiles.p402 import State402

from hal.cia402_od import (
    HEARTBEAT_PRODUCER,
    POSITION_ACTUAL,
    STATUSWORD,
    TORQUE_ACTUAL,
    VELOCITY_ACTUAL,
)

EVENTS_KEPT = 64
"""Fault events kept for ``/diagnostics`` and the summary (all are counted)."""


def state_of(statusword: int) -> str:
    """The CiA 402 power state a statusword reports (canopen's masks), ``UNKNOWN`` if none."""
    for state, (mask, bits) in State402.SW_MASK.items():
        if statusword & mask == bits:
            return state
    return "UNKNOWN"


@dataclass(frozen=True)
class FaultEvent:
    """One fault the master saw."""

    t_ns: int
    node: int
    label: str
    """``emcy_XXXX`` (the EMCY error code, hex), ``heartbeat_lost`` or ``rebooted``."""
    detail: str


@dataclass
class FaultLog:
    """Faults of one run: counted by label, the last :data:`EVENTS_KEPT` kept."""

    counts: Counter[str] = field(default_factory=Counter)
    events: deque[FaultEvent] = field(default_factory=lambda: deque(maxlen=EVENTS_KEPT))
    resets: int = 0
    """EMCY *error reset* messages (code 0): a drive left FAULT; not a fault."""
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self, event: FaultEvent) -> None:
        with self._lock:
            self.counts[event.label] += 1
            self.events.append(event)

    def as_dict(self) -> dict[str, object]:
        with self._lock:
            return {
                "counts": dict(self.counts),
                "emcy_resets": self.resets,
                "events": [e.__dict__ for e in self.events],
            }


@dataclass
class Sample:
    """The newest TPDO values of one drive (raw object values)."""

    statusword: int = 0
    position: int = 0
    velocity: int = 0
    torque: int = 0
    sync: dict[int, int] = field(default_factory=dict)
    """TPDO number -> the SYNC count it answered (the count when it arrived)."""
    t_ns: dict[int, int] = field(default_factory=dict)
    """TPDO number -> receive time."""


class NodeWatch:
    """One drive as heard on the bus (callbacks on canopen's receive thread; read the
    snapshot under :attr:`cond`)."""

    def __init__(
        self,
        node: canopen.RemoteNode,
        faults: FaultLog,
        cond: threading.Condition,
        now_ns: Callable[[], int],
        sync_count: Callable[[], int],
    ) -> None:
        self.node = node
        self.faults = faults
        self.cond = cond
        self.now_ns = now_ns
        self.sync_count = sync_count
        self.sample = Sample()
        self.booted = threading.Event()
        self.nmt_state: int | None = None
        self.heartbeat_ns: int | None = None
        self.heartbeat_limit_ns: int | None = None
        """Set once the drive produces heartbeats: older than this means lost."""
        self.lost = False
        self.started = False
        """NMT start was sent: a boot-up from now on is a reboot (a fault)."""
        node.nmt.add_heartbeat_callback(self._on_heartbeat)
        node.emcy.add_callback(self._on_emcy)

    def watch_tpdos(self) -> None:
        """Follow TPDO1 and TPDO2 (after they were mapped)."""
        for number in (1, 2):
            pdo = self.node.tpdo[number]
            if self._on_tpdo not in pdo.callbacks:
                pdo.add_callback(self._on_tpdo)

    def _on_tpdo(self, pdo: canopen.pdo.PdoMap) -> None:
        now, k = self.now_ns(), self.sync_count()
        with self.cond:
            s = self.sample
            if pdo is self.node.tpdo[1]:
                number = 1
                s.statusword, s.position = int(pdo[STATUSWORD].raw), int(pdo[POSITION_ACTUAL].raw)
            else:
                number = 2
                s.velocity, s.torque = int(pdo[VELOCITY_ACTUAL].raw), int(pdo[TORQUE_ACTUAL].raw)
            s.sync[number], s.t_ns[number] = k, now
            self.cond.notify_all()

    def _on_heartbeat(self, state: int) -> None:
        now = self.now_ns()
        with self.cond:
            self.heartbeat_ns, self.nmt_state = now, state
            self.lost = False
        if state == 0:
            self.booted.set()
            if self.started:
                self.faults.add(FaultEvent(now, self.node.id, "rebooted", "boot-up while running"))

    def _on_emcy(self, err: EmcyError) -> None:
        if err.code & 0xFF00 == 0:
            self.faults.resets += 1
            return
        detail = f"{err} (error register 0x{err.register:02X})"
        self.faults.add(FaultEvent(self.now_ns(), self.node.id, f"emcy_{err.code:04X}", detail))

    def check_heartbeat(self, now_ns: int) -> bool:
        """Whether the drive's heartbeat is lost at ``now_ns`` (a new loss is a fault)."""
        limit = self.heartbeat_limit_ns
        if limit is None or self.heartbeat_ns is None:
            return False
        with self.cond:
            if self.lost or now_ns - self.heartbeat_ns <= limit:
                return self.lost
            self.lost = True
        detail = f"last heartbeat {(now_ns - self.heartbeat_ns) / 1e6:.0f} ms ago"
        self.faults.add(FaultEvent(now_ns, self.node.id, "heartbeat_lost", detail))
        return True

    @property
    def nmt_label(self) -> str:
        return "none" if self.nmt_state is None else NMT_STATES.get(self.nmt_state, "unknown")


def heartbeat_dictionary() -> canopen.ObjectDictionary:
    """The controller's own object dictionary: just the producer heartbeat time 0x1017, so
    canopen's NMT slave can produce the heartbeat the drives consume."""
    od = canopen.ObjectDictionary()
    var = canopen.objectdictionary.ODVariable("Producer heartbeat time", HEARTBEAT_PRODUCER, 0)
    var.data_type = canopen.objectdictionary.UNSIGNED16
    var.access_type = "rw"
    var.default = 0
    od.add_object(var)
    return od


__all__ = [
    "EVENTS_KEPT",
    "FaultEvent",
    "FaultLog",
    "NodeWatch",
    "Sample",
    "heartbeat_dictionary",
    "state_of",
]
