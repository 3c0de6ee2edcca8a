"""One emulated CiA 402 servo drive in cyclic synchronous torque mode: a canopen LocalNode.

The object dictionary is :mod:`hal.cia402_od`'s table. What canopen's ``LocalNode`` does not do
is done here: the PDOs on SYNC (:mod:`plant_emulator.cia402.pdo`), boot-up and the return to
PRE-OPERATIONAL after an NMT reset, the power state machine
(:mod:`plant_emulator.cia402.power_state`), the live values of 0x6041/0x6061/0x6064/0x606C/
0x6077, and the fault monitors. The physics is not here: :class:`~plant_emulator.cia402.rig.
Cia402Rig` steps the one world on each SYNC and hands each drive its joint's state.

Fault reactions (torque off, FAULT, EMCY; the drive stays in FAULT until a fault reset):

* SYNC loss: once a SYNC arrived in NMT OPERATIONAL, no SYNC for ``sync_loss_periods`` times
  the cycle (0x1006 if set, else 0x60C2), or for ``sync_timeout_s`` in lockstep -> EMCY 0x8700
  (sync controller);
* heartbeat loss: 0x1016.1 = (node id << 16) | ms; after the first heartbeat of that node, a gap
  longer than ms (in lockstep at least ``sync_timeout_s``: the world waits for the controller,
  a late heartbeat on a loaded host is not a lost one) -> EMCY 0x8130 (life guard / heartbeat
  error);
* enabling operation with a 0x60C2 that is not the emulator's control period -> EMCY 0x6320
  (parameter error): the world steps one control period per SYNC, so a drive told otherwise
  refuses to follow.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import canopen
from canopen.sdo import SdoAbortedError

from hal import cia402_od as cia
from plant_emulator.cia402.pdo import ABORT_VALUE_RANGE, PdoService
from plant_emulator.cia402.power_state import PowerStateMachine

NMT_RESET_NODE = 0x81
NMT_RESET_COMMUNICATION = 0x82
NMT_PRE_OPERATIONAL = 0x80
_ACCEPTED_MODES = (cia.NO_MODE, cia.CST_MODE)
_COMMUNICATION_OBJECTS = range(0x1000, 0x2000)


class EmulatedDrive(canopen.LocalNode):
    """A CiA 402 drive for joint ``joint`` (0-based) of the emulated arm.

    ``params`` are its object dictionary's values, ``period_s`` the control period the world
    steps per SYNC, ``tau_max_nm`` the amplifier's peak torque (the arm model's limit), ``clock``
    the monotonic clock of the monitors (injectable for tests), ``lock`` the rig's lock that
    serialises the bus thread and the monitor thread."""

    def __init__(
        self,
        node_id: int,
        joint: int,
        *,
        params: cia.DriveParameters,
        period_s: float,
        tau_max_nm: float,
        sync_loss_periods: float,
        sync_timeout_s: float | None = None,
        clock: Callable[[], float],
        lock: threading.RLock,
    ) -> None:
        super().__init__(node_id, cia.build_od(node_id, params))
        self.joint = joint
        self.period_s = period_s
        self.tau_max_nm = tau_max_nm
        self.sync_loss_periods = sync_loss_periods
        self.sync_timeout_s = sync_timeout_s
        """Lockstep: the SYNC-loss limit in seconds instead of ``sync_loss_periods`` cycles (a
        controller that paces the world may take longer than a period over a tick), and the
        least heartbeat-loss limit."""
        self.clock = clock
        self.lock = lock
        self.power = PowerStateMachine(
            quick_stop_option=lambda: self._value(cia.QUICK_STOP_OPTION),
            enable_check=self._enable_check,
        )
        self.pdos = PdoService(self, self._send_emcy)
        self.q = 0.0
        self.dq = 0.0
        self.torque_permille = 0
        """0x6077: the torque applied since the last SYNC, per mille of 0x6076."""
        self._last_sync: float | None = None
        self._heartbeat: tuple[int, float] | None = None  # (node id, seconds)
        self._last_heartbeat: float | None = None
        self.on_fault: Callable[[int, int], None] | None = None
        """Told (node id, EMCY code) of each fault as it happens (the command prints it)."""
        self.emcys: list[int] = []
        """Every EMCY code sent, in order (0 = error reset)."""
        self.last_sync_s: float | None = None
        """Clock time of the last SYNC seen while operational (kept across a fault)."""
        self.torque_off: tuple[int, float, float | None] | None = None
        """The last fault that took the torque away: (EMCY code, clock time, time since the
        last SYNC in s, None before any SYNC), for the run's account of a lost controller."""
        self.add_read_callback(self._read)
        self.add_write_callback(self._write)

    # -- network ------------------------------------------------------------------------------
    def associate_network(self, network: canopen.Network) -> None:
        super().associate_network(network)
        network.subscribe(0, self._on_nmt)  # after the NmtSlave's own handler
        self.pdos.reload()

    def remove_network(self) -> None:
        if self.has_network():
            self.nmt.stop_heartbeat()
            self.pdos.close()
            self._watch_heartbeat(None)
            self.network.unsubscribe(0, self._on_nmt)
        super().remove_network()

    def boot(self) -> None:
        """Boot-up message, then PRE-OPERATIONAL (and the heartbeat producer, 0x1017)."""
        self.nmt.send_command(NMT_RESET_NODE)  # state INITIALISING: sends the boot-up
        self.nmt.send_command(NMT_PRE_OPERATIONAL)

    def _on_nmt(self, _can_id: int, data: bytearray, _timestamp: float) -> None:
        command, node_id = data[0], data[1]
        if node_id not in (0, self.id):
            return
        with self.lock:
            if command in (NMT_RESET_NODE, NMT_RESET_COMMUNICATION):
                self._reset(node=command == NMT_RESET_NODE)
                self.boot()
            if self.nmt.state != "OPERATIONAL":
                self._last_sync = None

    def _reset(self, *, node: bool) -> None:
        """Power-on values of the communication objects (every object for a node reset)."""
        for index in list(self.data_store):
            if node or index in _COMMUNICATION_OBJECTS:
                del self.data_store[index]
        self._watch_heartbeat(None)
        self.pdos.reload()
        if node:
            self.new_run(self.q, self.dq)

    def new_run(self, q: float, dq: float) -> None:
        """A scenario reset: SWITCH ON DISABLED with no fault, torque off, watchdogs disarmed
        (the heartbeat consumer rearms at the next heartbeat), the joint at ``q``, ``dq``."""
        with self.lock:
            self.power = PowerStateMachine(
                quick_stop_option=lambda: self._value(cia.QUICK_STOP_OPTION),
                enable_check=self._enable_check,
            )
            self.torque_permille = 0
            self._last_sync = None
            self._last_heartbeat = None
            self.q, self.dq = q, dq

    @property
    def operational(self) -> bool:
        return self.nmt.state == "OPERATIONAL"

    # -- object dictionary --------------------------------------------------------------------
    def _value(self, index: int, subindex: int = 0) -> int:
        obj = self.object_dictionary[index]
        var = obj if subindex == 0 and not hasattr(obj, "subindices") else obj[subindex]
        return var.decode_raw(self.get_data(index, subindex))

    def increments_per_rad(self) -> float:
        return cia.increments_per_rad(
            self._value(cia.ENCODER_RESOLUTION, 1),
            self._value(cia.ENCODER_RESOLUTION, 2),
            self._value(cia.GEAR_RATIO, 1),
            self._value(cia.GEAR_RATIO, 2),
        )

    def mode(self) -> int:
        return self._value(cia.MODES_OF_OPERATION)

    def cycle_period_s(self) -> float:
        """The SYNC cycle the drive expects: 0x1006 (us) if set, else 0x60C2."""
        cycle_us = self._value(cia.CYCLE_PERIOD)
        if cycle_us:
            return cycle_us * 1e-6
        return cia.interpolation_seconds(*self._interpolation())

    def _interpolation(self) -> tuple[int, int]:
        return self._value(cia.INTERPOLATION_PERIOD, 1), self._value(cia.INTERPOLATION_PERIOD, 2)

    def _read(self, index: int, subindex: int, od: object) -> int | None:
        if index == 0x6041:
            return self.power.statusword(target_used=self.mode() == 10)
        if index == 0x6061:
            return self.mode()
        if index == 0x6064:
            return round(self.q * self.increments_per_rad())
        if index == 0x606C:
            return round(self.dq * self.increments_per_rad())
        if index == 0x6077:
            return self.torque_permille
        if index == 0x603F:
            return self.power.error_code
        if index == 0x1001:
            return self._error_register()
        return None

    def _error_register(self) -> int:
        code = self.power.error_code
        if not code:
            return 0
        register = 0x01  # generic
        if code >> 8 in (0x81, 0x82):
            register |= 0x10  # communication
        if code >> 8 == 0x87:
            register |= 0x20  # device profile specific
        return register

    def _write(self, index: int, subindex: int, od: object, data: bytes) -> None:
        self.pdos.check_write(index, subindex, data)
        value = od.decode_raw(data) if isinstance(od, canopen.objectdictionary.ODVariable) else 0
        if index == 0x6060 and value not in _ACCEPTED_MODES:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        if index == 0x605A and not 0 <= value <= 8:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        if ((index in (0x608F, 0x6091) and subindex in (1, 2)) or index == 0x6076) and value == 0:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        if index == 0x6040:
            with self.lock:
                was_faulted = self.power.faulted
                self.power.controlword(value)
                if was_faulted and not self.power.faulted:
                    self._send_emcy(0)  # error reset
                if not self.power.torque_enabled:
                    self.torque_permille = 0
        if index == 0x1016 and subindex == 1:
            node_id, ms = (value >> 16) & 0x7F, value & 0xFFFF
            self._watch_heartbeat((node_id, ms / 1000.0) if node_id and ms else None)

    def set_data(
        self, index: int, subindex: int, data: bytes, check_writable: bool = False
    ) -> None:
        super().set_data(index, subindex, data, check_writable)
        self.pdos.after_write(index)

    # -- monitors -----------------------------------------------------------------------------
    def _watch_heartbeat(self, consumer: tuple[int, float] | None) -> None:
        if self._heartbeat is not None:
            self.network.unsubscribe(0x700 + self._heartbeat[0], self._on_heartbeat)
        self._heartbeat = consumer
        self._last_heartbeat = None
        if consumer is not None:
            self.network.subscribe(0x700 + consumer[0], self._on_heartbeat)

    def _on_heartbeat(self, _can_id: int, _data: bytearray, _timestamp: float) -> None:
        with self.lock:
            self._last_heartbeat = self.clock()

    def poll(self, now: float) -> None:
        """Check the SYNC and heartbeat monitors at time ``now`` (the rig's monitor thread)."""
        with self.lock:
            sync_limit = self.sync_timeout_s or self.sync_loss_periods * self.cycle_period_s()
            if (
                self._last_sync is not None
                and self.operational
                and now - self._last_sync > sync_limit
            ):
                self._last_sync = None
                self.fault(cia.EMCY_SYNC)
            beat, consumer = self._last_heartbeat, self._heartbeat
            if (
                consumer is not None
                and beat is not None
                and now - beat > max(consumer[1], self.sync_timeout_s or 0.0)
            ):
                self._last_heartbeat = None
                self.fault(cia.EMCY_HEARTBEAT)

    def fault(self, code: int) -> None:
        """Torque off and FAULT with EMCY ``code`` (no EMCY when already faulted)."""
        with self.lock:
            if self.power.fault(code):
                self.torque_permille = 0
                now = self.clock()
                since = None if self.last_sync_s is None else now - self.last_sync_s
                self.torque_off = (code, now, since)
                self._send_emcy(code)
                if self.on_fault is not None:
                    self.on_fault(self.id, code)

    def _send_emcy(self, code: int) -> None:
        self.emcys.append(code)
        self.emcy.send(code, self._error_register())

    def _enable_check(self) -> int | None:
        value, index = self._interpolation()
        if abs(cia.interpolation_seconds(value, index) - self.period_s) > 0.5 * 10.0**index:
            return cia.EMCY_PARAMETER  # 0x60C2 does not say the world's control period
        return None

    # -- the SYNC -------------------------------------------------------------------------------
    def torque_nm(self) -> float:
        """The torque the drive applies now (0 unless OPERATION ENABLED in CST)."""
        return self.torque_permille * self._value(cia.RATED_TORQUE) / 1e6

    def on_sync(self, count: int, now: float, q: float, dq: float) -> None:
        """SYNC ``count`` (the world has stepped to it; ``q``, ``dq`` are this joint's state):
        latch the RPDOs, take the state and the new torque, then send the TPDOs."""
        with self.lock:
            operational = self.operational
            if operational:
                self._last_sync = self.last_sync_s = now
            self.power.tick()
            self.pdos.latch(operational)
            self.q, self.dq = q, dq
            self.torque_permille = self._commanded_permille()
            if operational:
                self.pdos.transmit(count)

    def _commanded_permille(self) -> int:
        if not self.power.torque_enabled or self.mode() != cia.CST_MODE:
            return 0
        rated = self._value(cia.RATED_TORQUE)
        limit = min(self._value(cia.MAX_TORQUE), int(self.tau_max_nm * 1e6 / rated))
        return max(-limit, min(limit, self._value(cia.TARGET_TORQUE)))
