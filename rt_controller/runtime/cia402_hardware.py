"""The ``cia402`` profile of the hardware seam (:class:`hal.hardware_interface.HardwareInterface`):
two CiA 402 drives in cyclic synchronous torque over CANopen (:mod:`hal.cia402_master`, on the
``canopen`` library), the image features over zenoh (:class:`FeatureLink`; with the rest of
:class:`~rt_controller.runtime.hardware_base.HardwareBase`).

Per period the bus carries RPDO(k-1) -> SYNC k -> TPDOs(k): the drives latch the torque at the
SYNC and answer it with their statusword, position, velocity and torque. In lockstep
:meth:`Cia402Hardware.step` sends SYNC k (the emulated world steps one period on it) and waits
for the TPDOs and the features of period k; in realtime :meth:`Cia402Hardware.write` sends the
SYNC right after the tick's RPDO, so the torque is latched at once and the TPDOs are in before
the next release.

CANopen carries no MAC: nothing on this profile's CAN side is authenticated (the ``dsp``
profile's SecOC has no counterpart here); see docs/tutorials/cia402-drive.md.
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter
from typing import Any

from hal.bus import resolve_spec
from hal.cia402_master.master import Cia402Master, JointState
from hal.drive_state import MODE_ENABLED, MODE_FAULT
from hal.hardware_interface import InputJudge, Observation, StopFlag
from rt_controller.errors import ControllerError
from rt_controller.runtime.context import RunContext
from rt_controller.runtime.feature_link import FeatureLink
from rt_controller.runtime.hardware_base import ENABLE_TIMEOUT_S, NOTICE_AFTER_S, HardwareBase
from rt_controller.runtime.pacers import LOCKSTEP_FEATURE_TIMEOUT_S
from rt_controller.sample_stats import percentile

LOCKSTEP_TPDO_TIMEOUT_S = 1.0
"""Lockstep: how long a SYNC may wait for every drive's TPDOs."""
ENABLED = "OPERATION ENABLED"
DISARMED = "READY TO SWITCH ON"


class Cia402Hardware(HardwareBase):
    """The CANopen drives and the zenoh features of one run, from the control thread."""

    def __init__(
        self,
        ctx: RunContext,
        master: Cia402Master,
        features: FeatureLink,
        *,
        lockstep: bool,
        record_raw: bool = False,
    ) -> None:
        """``record_raw``: every CANopen frame sent and received goes to the log's
        ``/hal/can/tx`` and ``/hal/can/rx``, from the boot on (as the DSP profile's)."""
        super().__init__(ctx, features, lockstep=lockstep, record_raw=record_raw)
        self.master = master
        self.target: str | None = ENABLED
        """Where the controlwords steer: *operation enabled* (armed), *ready to switch on*
        (the operator disarmed), None (a fault: hold, no automatic reset)."""
        self._faults_seen: Counter[str] = Counter()
        self.deactivation: list[tuple[str, tuple[str, ...]]] = []
        """The steps of :meth:`deactivate` with the states the drives answered."""
        self._pending: int | None = None
        self._k0: int | None = None
        """Lockstep: the SYNC whose TPDOs found every drive enabled: period 0 of the run."""
        self._period0_due = False
        """Lockstep: a SYNC whose TPDOs :meth:`step` is still waiting for."""

    # --- lifecycle --------------------------------------------------------------------------
    def configure(self, stop: StopFlag) -> None:
        """Boot the drives (NMT, SDO, PDO maps, CST read back, NMT start, the controller's
        heartbeat) and subscribe to the features. The first features are awaited while arming
        (:meth:`activate`): the emulated world publishes its camera pose only on SYNC."""
        self._hook_raw_can(self.master.tap)
        m, can = self.master, resolve_spec(self.ctx.cfg.transport.can)

        def waiting() -> None:  # said once, when the boot-ups are slow: of the nodes still silent
            if silent := [str(w.node.id) for w in m.watches if not w.booted.is_set()]:
                ids, up_to = ", ".join(silent), f"up to {m.settings.boot_timeout_s:g} s"
                self.ctx.say(
                    f"waiting for the drives' boot-up on CAN {can} (node ids {ids}, {up_to})"
                )

        notice = threading.Timer(NOTICE_AFTER_S, waiting)
        try:
            m.boot(stop, on_wait=notice.start)
        finally:
            notice.cancel()
        self.features.attach()

    def activate(self, now_ns: int) -> bool:
        """One step of the arming walk: each drive's controlword one CiA 402 transition toward
        *operation enabled* (zero torque) and a SYNC that latches it; True once every drive
        reports it (realtime: and the first features are in). Realtime: one SYNC per release
        (counted in ``arming_ticks``); lockstep: the SYNC steps the world and this waits for
        its TPDOs."""
        clock = self.ctx.clock
        if self._enable_by is None:
            self.master.watch_controller()  # the drives fault if this process stops from now on
            self._start_arming()
        self.features.poll(clock.now_ns())
        enabled = self.master.steer(ENABLED)
        have_features = self.lockstep or self.features.features.latest is not None
        if enabled and have_features:
            self._k0, self._period0_due = self.master.sync_count, True
            return True
        if clock.now_ns() > self._enable_by:
            if enabled:
                raise ControllerError(
                    f"no image features (zenoh) within {ENABLE_TIMEOUT_S:g} s of arming: is "
                    f"`hil vision` running on the same zenoh endpoints?"
                )
            states = ", ".join(f"node {n.id}: {d['state']}" for n, d in self._drive_states())
            raise ControllerError(
                f"the drives did not enter operation enabled within {ENABLE_TIMEOUT_S:g} s "
                f"({states})"
            )
        self.master.send(None)
        k = self.master.sync()
        if self.lockstep:
            self.master.wait_tpdos(k, LOCKSTEP_TPDO_TIMEOUT_S)
        else:
            self.ctx.counters.arming_ticks += 1
        return False

    def _disarm(self) -> None:
        """Quick stop, disable operation, NMT pre-operational, the controller's heartbeat
        off (:meth:`Cia402Master.deactivate`)."""
        period_s = self.ctx.cfg.rates.control_period_ns / 1e9
        self.deactivation = self.master.deactivate(max(3 * period_s, 0.1))

    # --- pacing -----------------------------------------------------------------------------
    def wait_inputs(self, until_ns: int) -> None:
        """Realtime: the TPDOs come by canopen's receive thread; feed the features' ring
        until ``until_ns``."""
        self.features.poll(self.ctx.clock.now_ns())
        time.sleep(max(0, until_ns - self.ctx.clock.now_ns()) / 1e9)

    def step(self, timeout_s: float) -> int | None:
        """Lockstep: SYNC k (the world steps one period), then every drive's TPDOs of k and
        the features answering pose k; the period's index, or None when the drives did not
        answer within ``timeout_s`` (the next call waits for the same SYNC's answer, it sends
        none). Periods count from the SYNC whose TPDOs found every drive enabled (period 0:
        its state, the world at t = 0, nothing sent), as the emulated world's clock starts
        there: the tick's t matches the world's time (the poses' stamps)."""
        if self._period0_due and self._k0 is not None:
            # period 0: the TPDOs that found the drives enabled are the world at t = 0
            self._period0_due = False
            self.features.wait_pose(self._k0, LOCKSTEP_FEATURE_TIMEOUT_S)
            return 0
        k = self._pending if self._pending is not None else self.master.sync()
        if not self.master.wait_tpdos(k, timeout_s):
            self._pending = k  # wait again for this SYNC's answer: another would step the world
            return None
        self._pending = None
        self.features.wait_pose(k, LOCKSTEP_FEATURE_TIMEOUT_S)
        return k - (self._k0 or 0)

    # --- read and write ---------------------------------------------------------------------
    def read(self, now_ns: int, judge: InputJudge) -> Observation:
        """The newest complete TPDO set and features, judged by ``judge``; the drive mode
        (a fault holds the controlwords: no automatic reset)."""
        self.features.poll(self.ctx.clock.now_ns())
        js = self.master.joint_state()
        mode = self.master.mode(now_ns)
        self._count_faults()
        if mode == MODE_FAULT and self.target == ENABLED:
            self.target = None
        state_new = js is not None and self._arrived(js.sync)
        age_ms = math.nan if js is None else (now_ns - js.sync_ns) / 1e6
        limit = judge.status_limit_s
        silent = js is None or (limit is not None and age_ms > limit * 1e3)
        mode = self._tick_mode(mode, mode == MODE_ENABLED and silent)
        stale = js is None or age_ms > judge.state_limit_s * 1e3
        state, state_ns = (None, None) if stale else (js, js.sync_ns)
        return self._observation(
            now_ns, judge, state, state_ns, age_ms, mode, state_new, drives=self._drive_fields(js)
        )

    def write(self, tau: tuple[float, float], *, sync: int | None, release_ns: int) -> None:
        """The tick's torque in RPDO1 with the controlword of the run's target; realtime: the
        SYNC that latches it, at once."""
        if self.target is not None:
            self.master.steer(self.target)
        self.master.send(tau)
        if sync is None:
            self.master.sync()

    def command(self, action: str) -> str | None:
        """``disarm``: *shutdown* (ready to switch on, torque off) until ``arm``; ``arm``:
        the walk to *operation enabled* again, resetting a fault; ``mark``: nothing."""
        if action == "disarm":
            if self.target == DISARMED:
                return "already disarmed by the operator"
            self.target = DISARMED
        elif action == "arm":
            if self.target == ENABLED and self.master.mode(self.ctx.clock.now_ns()) == MODE_ENABLED:
                return "already armed"
            self.target = ENABLED
        return None

    def diagnostics(self) -> dict[str, dict[str, Any]]:
        """The ``/diagnostics`` blocks of the DSP profile's names: ``can_rx`` (SYNCs sent;
        CANopen frames carry no MAC, so nothing is judged), ``features``, and ``dsp``: the
        drives (NMT and power state, units, limits), their faults, the SYNC interval and the
        SYNC-to-TPDO latency (median, p99, µs), the deactivation's steps."""
        m = self.master
        block: dict[str, Any] = {"profile": "cia402"}
        mode = m.mode(self.ctx.clock.now_ns())
        block.update(mode=mode, torque_enabled=mode == MODE_ENABLED, **m.diagnostics())
        block["deactivation"] = [list(step) for step in self.deactivation]
        for name, samples in (
            ("sync_interval_us", list(m.sync_intervals_us)),
            ("sync_to_tpdo_us", list(m.tpdo_latency_us)),
        ):
            block[f"{name}_median"] = percentile(samples, 50)
            block[f"{name}_p99"] = percentile(samples, 99)
        return {
            "can_rx": {"authenticated": False, "syncs_sent": m.sync_count},
            "features": self.features.as_dict(),
            "dsp": block,
        }

    # --- helpers ----------------------------------------------------------------------------
    def _actuation_delay_ms(self) -> float:
        """How long after its state the tick's torque starts to act, beyond the state's age.
        Lockstep: the state is sampled at the tick (age 0) and the torque is latched by the
        next step's SYNC, one period on. Realtime: the SYNC follows the RPDO at once, so the
        torque acts when written and the state's age (since its SYNC, about one period)
        already covers the delay."""
        return self.ctx.cfg.rates.control_period_ns / 1e6 if self.lockstep else 0.0

    def _drive_fields(self, js: JointState | None) -> dict[str, Any] | None:
        """The cycle record's ``drive_*`` fields (``cycle_schema.json``): each drive's power
        state, statusword and torque actual from the TPDO set ``js``, the controlword and
        target torque of the last RPDO sent; None before the first TPDO set."""
        if js is None:
            return None
        m = self.master
        return {
            "drive_state_1": js.states[0],
            "drive_state_2": js.states[1],
            "drive_statusword": list(js.statuswords),
            "drive_controlword": list(m.controlwords),
            "drive_target_torque": list(m.targets),
            "drive_torque_actual": list(js.torques_per_mille),
            "drive_sync": js.sync,
        }

    def _count_faults(self) -> None:
        """New faults of the drives (EMCY codes, heartbeat loss, reboot) into the run's
        ``dsp_faults`` (the summary's, which make a run not clean)."""
        counts = Counter(self.master.faults.counts)
        new = counts - self._faults_seen
        if new:
            self.ctx.counters.dsp_faults.update(new)
            self._faults_seen = counts

    def _drive_states(self) -> list[tuple[Any, dict[str, Any]]]:
        drives = self.master.diagnostics()["drives"]
        return [(n, drives[str(n.id)]) for n in self.master.nodes]


__all__ = ["Cia402Hardware"]
