"""The CANopen master of the ``cia402`` profile: one :class:`canopen.Network` on the run's
python-can bus, one :class:`~canopen.profiles.p402.BaseNode402` per joint, canopen's SYNC
producer, the controller's heartbeat (a canopen NMT slave), and per tick the RPDO (controlword,
target torque) out and the TPDOs (statusword, position, velocity, torque) in.

Timing: every PDO is synchronous. A drive latches the RPDO at the next SYNC and answers each
SYNC with its TPDOs, so the bus carries, per period, RPDO(k-1) -> SYNC k -> TPDOs(k). In
lockstep the caller sends SYNC k when it wants period k (:meth:`sync` then
:meth:`wait_tpdos`); in realtime it sends the SYNC right after the tick's RPDO, so the torque
is latched at once and the TPDOs are there before the next release.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import canopen
from canopen.nmt import NmtError
from canopen.profiles.p402 import BaseNode402, State402

from hal.can_tap import FrameTap
from hal.cia402_frames import SYNC_ID
from hal.cia402_master import boot, eds
from hal.cia402_master.units import DriveUnits
from hal.cia402_master.watch import (
    FaultLog,
    NodeWatch,
    heartbeat_dictionary,
    state_of,
)
from hal.cia402_od import CONTROLWORD, TARGET_TORQUE
from hal.config.cia402 import CONTROLLER_NODE_ID
from hal.drive_state import MODE_DISARMED, MODE_ENABLED, MODE_FAULT, MODE_NO_STATUS
from hal.errors import HalDriveError

CW_FAULT_RESET_BIT = 0x80
TOWARD_ENABLED = {
    "SWITCH ON DISABLED": "READY TO SWITCH ON",
    "READY TO SWITCH ON": "SWITCHED ON",
    "SWITCHED ON": "OPERATION ENABLED",
    "OPERATION ENABLED": "OPERATION ENABLED",
    "QUICK STOP ACTIVE": "OPERATION ENABLED",
    "FAULT": "SWITCH ON DISABLED",
}
"""The next power state on the way to *operation enabled* (CiA 402 transitions 2, 3, 4, 16,
15); the controlword of each step is canopen's ``State402.TRANSITIONTABLE``."""
FAULT_STATES = ("FAULT", "FAULT REACTION ACTIVE")
NOTIFIER_CYCLE_S = 0.1
"""canopen's receive thread looks at its stop request this often (its default, 1 s, would
make every close take that long)."""
HEARTBEAT_MS = 100
"""Producer heartbeat time of the drives and of the controller (CiA 301 0x1017)."""
CONSUMER_PERIODS = 5
"""A heartbeat is lost after this many producer periods (the drives' 0x1016 time, the
controller's check): 500 ms. The heartbeat is the slow backstop (a thread of a process on a
loaded host may stall for a few hundred ms, the control thread does not); a controller that
stops ticking is caught within 3 periods by the drives' SYNC monitoring."""
TIMING_KEPT = 100_000
"""SYNC intervals and SYNC-to-TPDO latencies kept for the run's statistics."""
OTHER_MASTER_LISTEN_S = 3 * HEARTBEAT_MS / 1000
"""How long the bus is listened to for another master (its SYNC, or a heartbeat of the
controller's node id) before the first NMT command: three of our heartbeat periods."""
RELEASE_ON_CLOSE_S = 0.5
"""How long :meth:`Cia402Master.close` waits for each drive's pre-operational heartbeat."""


def controlword_toward(target: str, statusword: int, last: int) -> int:
    """The controlword for the next SYNC, one CiA 402 transition toward ``target``:
    ``OPERATION ENABLED`` (the arming walk; a FAULT is reset by a rising edge of bit 7, so one
    answered with bit 7 already set gets it cleared first) or ``READY TO SWITCH ON`` (disarm:
    *shutdown*)."""
    if target != "OPERATION ENABLED":
        return State402.CW_SHUTDOWN
    state = state_of(statusword)
    if state == "FAULT" and last & CW_FAULT_RESET_BIT:
        return State402.CW_DISABLE_VOLTAGE
    nxt = TOWARD_ENABLED.get(state)
    if nxt is None:  # not ready, fault reaction active: nothing to ask yet
        return State402.CW_DISABLE_VOLTAGE
    if nxt == state:
        return State402.CW_OPERATION_ENABLED
    return State402.TRANSITIONTABLE[(state, nxt)]


@dataclass(frozen=True)
class JointState:
    """The joints as the newest complete set of TPDOs reported them (SI units)."""

    q: tuple[float, ...]
    dq: tuple[float, ...]
    tau: tuple[float, ...]
    """Torque actual 0x6077, N·m at the joint."""
    states: tuple[str, ...]
    """Each drive's power state."""
    sync: int
    """The SYNC these TPDOs answered."""
    sync_ns: int
    """When that SYNC was sent (the drives sample at the SYNC)."""
    statuswords: tuple[int, ...] = ()
    """Each drive's statusword 0x6041 (raw)."""
    torques_per_mille: tuple[int, ...] = ()
    """Each drive's torque actual 0x6077 (raw: per mille of the rated torque 0x6076)."""


class Cia402Master:
    """The drives of one rig on one bus (see the module docstring)."""

    def __init__(
        self,
        bus: Any,
        node_ids: Sequence[int],
        dictionary: Callable[[int], Any],
        settings: boot.BootSettings,
        torque_limits_nm: Sequence[float],
        *,
        now_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        """``dictionary(node_id)``: the node's object dictionary (an EDS path or a
        :class:`canopen.ObjectDictionary`); ``torque_limits_nm``: 0x6072 per joint."""
        if len(torque_limits_nm) != len(node_ids):
            raise HalDriveError(f"{len(node_ids)} node ids but {len(torque_limits_nm)} limits")
        self.settings = settings
        self.torque_limits_nm = tuple(float(t) for t in torque_limits_nm)
        self.now_ns = now_ns
        self.tap = FrameTap(bus)
        """The bus as canopen uses it: its hooks show the run's log every frame."""
        self.network = canopen.Network(self.tap)
        self.network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
        self.cond = threading.Condition()
        self.faults = FaultLog()
        self.sync_count = 0
        self.sync_ns: dict[int, int] = {}
        self.nodes: list[BaseNode402] = []
        self.watches: list[NodeWatch] = []
        for node_id in node_ids:
            node = BaseNode402(int(node_id), dictionary(int(node_id)))
            self.network.add_node(node)
            self.nodes.append(node)
            self.watches.append(
                NodeWatch(node, self.faults, self.cond, now_ns, lambda: self.sync_count)
            )
        self.heartbeat = canopen.LocalNode(settings.master_id, heartbeat_dictionary())
        self.network.add_node(self.heartbeat)
        self.units: list[DriveUnits] = []
        self.limits: list[int] = []
        self.controlwords = [State402.CW_DISABLE_VOLTAGE] * len(self.nodes)
        self.targets = [0] * len(self.nodes)
        """The target torque 0x6071 of each drive's last RPDO (raw, per mille)."""
        self.sync_intervals_us: deque[float] = deque(maxlen=TIMING_KEPT)
        self.tpdo_latency_us: deque[float] = deque(maxlen=TIMING_KEPT)
        self._timed_sync = 0
        self._last_state: JointState | None = None
        self.connected = self.operational = False

    @classmethod
    def from_config(
        cls, cfg: Any, bus: Any, *, now_ns: Callable[[], int] = time.monotonic_ns
    ) -> Cia402Master:
        """The master of ``cfg`` (a :class:`hal.config.RigConfig`): the drives of
        ``[cia402]``, each described by its EDS (``cia402.eds_1``, ``eds_2``; the shipped one
        when empty), 0x6072 from ``robot.tau_max``, 0x60C2 and the SYNC period from
        ``rates.control_hz``."""
        settings = boot.BootSettings(
            master_id=CONTROLLER_NODE_ID,
            heartbeat_ms=HEARTBEAT_MS,
            consumer_ms=CONSUMER_PERIODS * HEARTBEAT_MS,
            period_s=1.0 / cfg.rates.control_hz,
        )
        ods = {
            node: eds.drive_dictionary(key, value, node) for key, value, node in eds.configured(cfg)
        }
        return cls(
            bus,
            list(ods),
            ods.__getitem__,
            settings,
            cfg.robot.tau_max,
            now_ns=now_ns,
        )

    # --- boot --------------------------------------------------------------------------------
    def boot(self, stop: Any | None = None, on_wait: Callable[[], None] | None = None) -> None:
        """Reset, configure and map every drive, CST with 0x6061 read back, NMT start, and the
        controller's heartbeat on (see :mod:`hal.cia402_master.boot`); ``on_wait()`` once the
        resets are sent, before the wait for the boot-ups."""
        if not self.connected:
            self.network.connect()
            self.connected = True
        s = self.settings
        with OtherMasters(self.network, s.master_id) as others:
            others.refuse(OTHER_MASTER_LISTEN_S)  # before a drive hears anything from us
            booted = {w.node.id: w.booted for w in self.watches}
            boot.reset_communication(self.nodes, booted, s.boot_timeout_s, stop, on_wait)
            self.units, self.limits = [], []
            joints = zip(self.nodes, self.watches, self.torque_limits_nm, strict=True)
            for node, watch, limit_nm in joints:
                units, limit = boot.configure(node, s, limit_nm)
                self.units.append(units)
                self.limits.append(limit)
                watch.heartbeat_limit_ns = CONSUMER_PERIODS * s.heartbeat_ms * 1_000_000
                boot.map_pdos(node)
                watch.watch_tpdos()
                boot.enter_cst(node)
            others.refuse(0.0)  # one that started during the boot: no NMT start under it
        self.heartbeat.nmt.state = "OPERATIONAL"
        self.heartbeat.nmt.start_heartbeat(s.heartbeat_ms)
        for node, watch in zip(self.nodes, self.watches, strict=True):
            node.nmt.state = "OPERATIONAL"
            watch.started = True
        self.operational = True

    # --- per period ----------------------------------------------------------------------------
    def sync(self) -> int:
        """Send SYNC (canopen's producer, once); its count (1, 2, ...)."""
        now = self.now_ns()
        with self.cond:
            prev = self.sync_ns.get(self.sync_count)
            self.sync_count += 1
            k = self.sync_count
            self.sync_ns[k] = now
            self.sync_ns.pop(k - 8, None)
        if prev is not None:
            self.sync_intervals_us.append((now - prev) / 1e3)
        self.network.sync.transmit()
        return k

    def _complete(self, k: int) -> bool:
        return all(w.sample.sync.get(1) == w.sample.sync.get(2) == k for w in self.watches)

    def wait_tpdos(self, k: int, timeout_s: float) -> bool:
        """Block until every drive's TPDO1 and TPDO2 answered SYNC ``k``; False on timeout."""
        deadline = time.monotonic() + timeout_s
        with self.cond:
            while not self._complete(k):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self.cond.wait(left)
        return True

    def send(self, torques_nm: Sequence[float] | None = None) -> None:
        """Each drive's RPDO1: its controlword and target torque (zero when ``torques_nm``
        is None), encoded by canopen, latched by the drive at the next SYNC."""
        for i, node in enumerate(self.nodes):
            pdo = node.rpdo[1]
            tau = 0.0 if torques_nm is None or not self.units else float(torques_nm[i])
            target = self.units[i].per_mille(tau, self.limits[i]) if tau else 0
            pdo[CONTROLWORD].raw = self.controlwords[i]
            pdo[TARGET_TORQUE].raw = self.targets[i] = target
            pdo.transmit()

    def steer(self, target: str) -> bool:
        """Set each drive's next controlword one transition toward ``target`` (``OPERATION
        ENABLED`` or ``READY TO SWITCH ON``) from its last statusword; True once all are
        there. Send them with :meth:`send`."""
        there = True
        with self.cond:
            words = [w.sample.statusword for w in self.watches]
            seen = [bool(w.sample.sync) for w in self.watches]
        for i, (word, have) in enumerate(zip(words, seen, strict=True)):
            if not have or state_of(word) != target:
                there = False
            if have:
                self.controlwords[i] = controlword_toward(target, word, self.controlwords[i])
        return there

    def joint_state(self) -> JointState | None:
        """The newest complete TPDO set (every drive answered the same SYNC; while the
        TPDOs of the newest SYNC are still arriving, the previous complete one), None before
        the first; records each SYNC's TPDO latency once."""
        with self.cond:
            samples = [w.sample for w in self.watches]
            ks = {k for s in samples for k in s.sync.values()}
            if len(ks) != 1 or any(len(s.sync) != 2 for s in samples):
                return self._last_state
            (k,) = ks
            sync_ns = self.sync_ns.get(k)
            last_ns = max(t for s in samples for t in s.t_ns.values())
            raw = [(s.statusword, s.position, s.velocity, s.torque) for s in samples]
        if sync_ns is None:
            return self._last_state
        if k != self._timed_sync:
            self._timed_sync = k
            self.tpdo_latency_us.append((last_ns - sync_ns) / 1e3)
        u = self.units
        self._last_state = JointState(
            q=tuple(u[i].position_rad(r[1]) for i, r in enumerate(raw)),
            dq=tuple(u[i].velocity_rad_s(r[2]) for i, r in enumerate(raw)),
            tau=tuple(u[i].torque_nm(r[3]) for i, r in enumerate(raw)),
            states=tuple(state_of(r[0]) for r in raw),
            sync=k,
            sync_ns=sync_ns,
            statuswords=tuple(r[0] for r in raw),
            torques_per_mille=tuple(r[3] for r in raw),
        )
        return self._last_state

    def mode(self, now_ns: int) -> str:
        """The rig's drive mode (:data:`hal.drive_state.MODES`): ``fault`` when a drive is in
        FAULT or its heartbeat is lost, ``enabled`` when every drive is in *operation
        enabled*, ``no_status`` before every drive answered a SYNC, else ``disarmed``."""
        lost = [w.check_heartbeat(now_ns) for w in self.watches]
        with self.cond:
            samples = [(bool(w.sample.sync), state_of(w.sample.statusword)) for w in self.watches]
        if any(lost) or any(have and st in FAULT_STATES for have, st in samples):
            return MODE_FAULT
        if not all(have for have, _ in samples):
            return MODE_NO_STATUS
        if all(st == "OPERATION ENABLED" for _, st in samples):
            return MODE_ENABLED
        return MODE_DISARMED

    # --- the end -------------------------------------------------------------------------------
    def deactivate(self, timeout_s: float) -> list[tuple[str, tuple[str, ...]]]:
        """Quick stop, then disable operation (a drive still in *operation enabled*:
        transition 5; one in *quick stop active*: disable voltage, transition 12), each
        latched by a SYNC, then NMT pre-operational (the drives stop watching SYNC), then the
        drives stop consuming the controller's heartbeat (0x1016.1 = 0) and it stops. Returns
        each step with the power states the drives answered (``none`` when silent). Safe to
        call twice or before :meth:`boot`."""
        if not self.operational:
            self.heartbeat.nmt.stop_heartbeat()
            return []
        self.operational = False
        steps: list[tuple[str, tuple[str, ...]]] = []
        n = len(self.nodes)
        self.controlwords = [State402.CW_QUICK_STOP] * n
        steps.append(("quick stop", self._latch(timeout_s)))
        self.controlwords = [
            State402.CW_SWITCH_ON if st == "OPERATION ENABLED" else State402.CW_DISABLE_VOLTAGE
            for st in steps[-1][1]
        ]
        steps.append(("disable operation", self._latch(timeout_s)))
        steps.extend(self.release(timeout_s))
        return steps

    def release(self, timeout_s: float) -> list[tuple[str, tuple[str, ...]]]:
        """NMT pre-operational (the drives stop watching SYNC and send no PDO), then the
        drives stop consuming the controller's heartbeat (0x1016.1 = 0), then it stops: the
        drives stay configured, torque off, and nothing faults them."""
        self.operational = False
        for node in self.nodes:
            node.nmt.state = "PRE-OPERATIONAL"
        states = tuple(self._heartbeat_in(n, "PRE-OPERATIONAL", timeout_s) for n in self.nodes)
        steps: list[tuple[str, tuple[str, ...]]] = [("pre-operational", states)]
        for node, watch in zip(self.nodes, self.watches, strict=True):
            watch.started = False
            try:
                boot.watch_controller(node, self.settings, on=False)
            except HalDriveError as exc:
                steps.append((f"node {node.id} kept its heartbeat consumer: {exc}", ()))
        self.heartbeat.nmt.stop_heartbeat()
        return steps

    def watch_controller(self) -> None:
        """Every drive consumes the controller's heartbeat from now on (0x1016.1): the
        first step of arming (:func:`boot.watch_controller` says why not at boot)."""
        for node in self.nodes:
            boot.watch_controller(node, self.settings, on=True)

    def check(
        self, stop: Any | None = None, on_wait: Callable[[], None] | None = None
    ) -> list[dict[str, Any]]:
        """Boot the drives as a run would (the maps read back, CST read back; ``on_wait`` as
        :meth:`boot`'s), describe each by SDO, and :meth:`release` them: no SYNC is sent, no
        drive is enabled."""
        self.boot(stop, on_wait)
        try:
            return [boot.describe(node) for node in self.nodes]
        finally:
            self.release(1.0)

    @staticmethod
    def _next_heartbeat(node: BaseNode402, timeout_s: float) -> str:
        """The NMT state of the node's next heartbeat (``none`` when it stays silent)."""
        try:
            return node.nmt.wait_for_heartbeat(timeout_s)
        except NmtError:
            return "none"

    @classmethod
    def _heartbeat_in(cls, node: BaseNode402, state: str, timeout_s: float) -> str:
        """The NMT state of the node's heartbeats until one says ``state`` or ``timeout_s``
        passes: the first heartbeat after an NMT command may have left before the drive took
        the command."""
        deadline = time.monotonic() + timeout_s
        seen = "none"
        while (left := deadline - time.monotonic()) > 0:
            seen = cls._next_heartbeat(node, left)
            if seen in (state, "none"):
                break
        return seen

    def _latch(self, timeout_s: float) -> tuple[str, ...]:
        """Send the controlwords with zero torque, SYNC, and the states that answered."""
        self.send(None)
        k = self.sync()
        self.wait_tpdos(k, timeout_s)
        with self.cond:
            return tuple(
                state_of(w.sample.statusword) if w.sample.sync.get(1) == k else "none"
                for w in self.watches
            )

    def close(self) -> None:
        """Drives booted and never deactivated (a run stopped between its boot and its first
        arming step) are released first (:meth:`release`), so none stays in NMT operational; then
        stop the heartbeat and the receive thread and shut the bus down."""
        try:
            if self.operational and self.connected:
                self.release(RELEASE_ON_CLOSE_S)
        finally:
            self._shut()

    def _shut(self) -> None:
        self.heartbeat.nmt.stop_heartbeat()
        if self.connected:
            self.connected = False
            self.network.disconnect()
        elif self.network.bus is not None:  # never connected: the bus is still ours to shut
            self.network.bus.shutdown()
            self.network.bus = None

    def diagnostics(self) -> dict[str, Any]:
        """Per drive: NMT and power state, statusword, units and torque limit; the faults."""
        drives = {}
        with self.cond:
            words = [w.sample.statusword for w in self.watches]
        for i, (node, watch) in enumerate(zip(self.nodes, self.watches, strict=True)):
            units = self.units[i] if i < len(self.units) else None
            drives[str(node.id)] = {
                "nmt": watch.nmt_label,
                "state": state_of(words[i]).lower(),
                "statusword": f"0x{words[i]:04X}",
                "heartbeat_lost": watch.lost,
                "increments_per_rad": units.increments_per_rad if units else None,
                "rated_torque_nm": units.joint_rated_torque_nm if units else None,
                "torque_limit_per_mille": self.limits[i] if i < len(self.limits) else None,
            }
        return {"drives": drives, "syncs": self.sync_count, **self.faults.as_dict()}


class OtherMasters:
    """While open: whether another master drives the bus, by its SYNC (COB-ID 0x080) or a
    heartbeat of the controller's node id. Booting under it would reset and remap drives it
    is running (and the dsp profile's emulator sends its Sync on 0x080 too)."""

    def __init__(self, network: canopen.Network, master_id: int) -> None:
        self.network = network
        self.master_id = master_id
        self.heartbeat_id = 0x700 + master_id  # CiA 301: NMT error control, 0x700 + node id
        self.heard = threading.Event()
        self.what = ""

    def _on_frame(self, can_id: int, _data: bytearray, _timestamp: float) -> None:
        if not self.heard.is_set():
            heartbeat = f"a heartbeat of node {self.master_id}"
            self.what = "SYNC" if can_id == SYNC_ID else heartbeat
            self.what += f" (COB-ID 0x{can_id:03X})"
            self.heard.set()

    def __enter__(self) -> OtherMasters:
        for can_id in (SYNC_ID, self.heartbeat_id):
            self.network.subscribe(can_id, self._on_frame)
        return self

    def __exit__(self, *_exc: object) -> None:
        for can_id in (SYNC_ID, self.heartbeat_id):
            self.network.unsubscribe(can_id, self._on_frame)

    def refuse(self, listen_s: float) -> None:
        """:class:`HalDriveError` when another master was heard (waiting up to ``listen_s``)."""
        if self.heard.wait(listen_s):
            raise HalDriveError(
                f"another CANopen master is on this bus ({self.what} heard): stop it first "
                f"(a running `hil controller` or `hil up`, a PLC, a vendor tool, or a "
                f"dsp-profile emulator), so its drives are not reset and remapped under it"
            )


__all__ = ["Cia402Master", "JointState", "OtherMasters", "controlword_toward"]
