"""Two emulated CiA 402 drives on the one physics world, paced by the controller's SYNC.

Lockstep by construction: each SYNC on the bus steps the world by one control period with the
torques the drives applied since the previous SYNC, then every drive latches its RPDOs (the new
controlword and target torque), takes its joint's state and sends its TPDOs. The world's clock
starts once every drive is in OPERATION ENABLED (:attr:`Cia402Rig.running`), as the emulated DSP
holds its period 0 until it is armed: the arming SYNCs do not move the scenario. So the TPDOs
after SYNC k carry q(t_k), dq(t_k) and the torque applied over [t_k, t_k+1], and a command that
reaches a drive between SYNCs acts from the next SYNC on. The step listener (the camera's
poses) hears the SYNC's arrival (the bus's receive stamp) as the time the stepped world is
valid for. A monitor thread polls the drives' SYNC and heartbeat watchdogs (tests poll with
their own clock instead).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from hal.cia402_master.units import interpolation_period
from hal.cia402_od import EMCY_POSITION_LIMIT, EMCY_VELOCITY_LIMIT, DriveParameters
from plant_emulator.cia402.drive import EmulatedDrive
from plant_emulator.world import World

if TYPE_CHECKING:
    import canopen

    from hal.config import RigConfig

SYNC_COB_ID = 0x80
"""The SYNC's COB-ID (0x1005 default)."""
MONITOR_POLLS_PER_PERIOD = 10
"""How often per control period the monitor thread checks the watchdogs."""

StepListener = Callable[[int, World, int], None]
"""Called after each SYNC's world step with the SYNC count, the world (camera poses) and the
SYNC's arrival on the rig's clock (ns): the time the stepped world's state is valid for."""


def sync_arrival(now_s: float, waited_s: float, period_s: float) -> float:
    """When a SYNC handled at ``now_s`` arrived: ``waited_s`` earlier (how long it waited since
    the bus stamped it: the kernel's receive stamp on socketcan and UDP) when that wait is
    plausible, 0 to one period; else ``now_s`` (a bus without receive stamps, a clock step)."""
    return now_s - waited_s if 0.0 <= waited_s < period_s else now_s


def drive_parameters(cfg: RigConfig, joint: int, tau_max_nm: float) -> DriveParameters:
    """The object-dictionary values of joint ``joint``'s drive from ``[cia402]`` and the rates;
    0x60C2 as the master writes it (:class:`~hal.errors.HalConfigError` for a control period it
    cannot write exactly)."""
    c = cfg.cia402
    rated_mnm = round(c.rated_torque[joint] * 1000)
    return DriveParameters(
        rated_torque_mnm=rated_mnm,
        max_torque_permille=min(0xFFFF, round(tau_max_nm * 1e6 / rated_mnm)),
        encoder_increments=c.encoder_increments,
        interpolation=interpolation_period(1.0 / cfg.rates.control_hz),
    )


class Cia402Rig:
    """The world and its two drives on ``network`` (a connected :class:`canopen.Network`);
    ``lockstep``: the controller paces the world with its SYNC and may pause longer than a
    period (``cia402.lockstep_sync_timeout_s`` is then the SYNC-loss limit)."""

    def __init__(
        self,
        cfg: RigConfig,
        network: canopen.Network,
        *,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
        on_step: StepListener | None = None,
        lockstep: bool = False,
        on_reset: Callable[[int | None], None] | None = None,
    ) -> None:
        self.cfg = cfg
        self.world = World(cfg)
        self._start_seed = self.world.seed
        self.network = network
        self.clock = clock
        self.wall_clock = wall_clock
        """The clock of python-can's frame timestamps (the wall clock)."""
        self.on_step = on_step
        self.on_reset = on_reset
        self.lock = threading.RLock()
        self.period_s = 1.0 / cfg.rates.control_hz
        self.substeps = cfg.rates.substeps
        tau_max = self.world.cfg.robot.tau_max  # the plant's amplifier limits
        self.drives: list[EmulatedDrive] = []
        for joint, node_id in enumerate((cfg.cia402.node_id_1, cfg.cia402.node_id_2)):
            drive = EmulatedDrive(
                node_id,
                joint,
                params=drive_parameters(cfg, joint, tau_max[joint]),
                period_s=self.period_s,
                tau_max_nm=tau_max[joint],
                sync_loss_periods=cfg.cia402.sync_loss_periods,
                sync_timeout_s=cfg.cia402.lockstep_sync_timeout_s if lockstep else None,
                clock=clock,
                lock=self.lock,
            )
            drive.q, drive.dq = float(self.world.q[joint]), float(self.world.dq[joint])
            self.drives.append(drive)
        self.syncs = 0
        """SYNCs received."""
        self.running = False
        """Whether the world's clock runs: from the SYNC after the one at which every drive is
        in OPERATION ENABLED (the scenario's t = 0 then, as the DSP holds its period 0 until
        it is armed), every SYNC steps it; the arming SYNCs before do not."""
        self._stop = threading.Event()
        self._monitor: threading.Thread | None = None

    def start(self, *, monitor: bool = True) -> None:
        """Put the drives on the network and boot them (boot-up messages, PRE-OPERATIONAL),
        then start the monitor thread. The physics kernels are loaded first, on a throw-away
        world, so the drives answer nothing before they can follow the SYNC without a JIT
        pause (which would trip the SYNC watchdog or undo a master's NMT start)."""
        World(self.cfg).hold(np.zeros(2), 1)
        with self.lock:
            for drive in self.drives:
                self.network.add_node(drive)
                drive.boot()
            self.network.subscribe(SYNC_COB_ID, self._on_sync)
        if monitor:
            self._monitor = threading.Thread(target=self._watch, name="cia402-monitor", daemon=True)
            self._monitor.start()

    def _watch(self) -> None:
        interval = self.period_s / MONITOR_POLLS_PER_PERIOD
        while not self._stop.wait(interval):
            self.poll()

    def poll(self, now: float | None = None) -> None:
        """Check every drive's SYNC and heartbeat watchdogs at ``now`` (default: the clock)."""
        now = self.clock() if now is None else now
        for drive in self.drives:
            drive.poll(now)

    def _on_sync(self, _can_id: int, _data: bytearray, timestamp: float) -> None:
        waited, seen = self.wall_clock() - timestamp, self.clock()
        with self.lock:
            now = self.clock()
            self.running = self.running or all(d.power.torque_enabled for d in self.drives)
            if self.running:
                tau = np.array([drive.torque_nm() for drive in self.drives])
                self.world.hold(tau, self.substeps)
                self._check_limits()
            self.syncs += 1
            for drive in self.drives:
                j = drive.joint
                drive.on_sync(self.syncs, now, float(self.world.q[j]), float(self.world.dq[j]))
        if self.on_step is not None:
            # the world after SYNC k is the arm at the SYNC, as a drive samples its position
            # there: its stamp is the SYNC's arrival on the bus, not when this thread got to
            # it, nor the end of the step and the TPDOs after it
            arrived = sync_arrival(seen, waited, self.period_s)
            self.on_step(self.syncs, self.world, round(arrived * 1e9))

    def _check_limits(self) -> None:
        """At the end of each control period, as the emulated DSP: a drive with operation
        enabled whose joint is beyond ``dsp.q_min``/``dsp.q_max`` (EMCY 0x8612) or faster than
        ``dsp.dq_max`` (EMCY 0x8400) faults. Each drive watches its own joint only."""
        limits = self.cfg.dsp
        for drive in self.drives:
            j = drive.joint
            if not drive.power.torque_enabled:
                continue
            if not limits.q_min[j] <= self.world.q[j] <= limits.q_max[j]:
                drive.fault(EMCY_POSITION_LIMIT)
            elif abs(self.world.dq[j]) > limits.dq_max[j]:
                drive.fault(EMCY_VELOCITY_LIMIT)

    def request_reset(self, seed: int | None = None) -> bool:
        """A scenario reset (the simulator-control channel, :mod:`hal.sim_control`; any
        thread), applied at once between SYNCs, as a freshly started emulator: the world back
        to the scenario's start with the camera noise of ``seed`` (None: the one at start), the
        SYNC count back to 0, every drive in SWITCH ON DISABLED with its fault cleared and its
        watchdogs disarmed. ``on_reset`` (the pose link) hears the seed."""
        with self.lock:
            self.world.seed = self._start_seed if seed is None else seed
            self.world.reset()
            self.running = False
            self.syncs = 0
            for drive in self.drives:
                drive.new_run(float(self.world.q[drive.joint]), float(self.world.dq[drive.joint]))
        if self.on_reset is not None:
            self.on_reset(seed)
        return True

    def torques(self) -> tuple[float, float]:
        """The torques the drives apply now, Nm."""
        with self.lock:
            return tuple(drive.torque_nm() for drive in self.drives)  # type: ignore[return-value]

    def close(self) -> None:
        """Stop the monitor, take the drives off the network (torque off, heartbeats stop)."""
        self._stop.set()
        if self._monitor is not None:
            self._monitor.join()
            self._monitor = None
        with self.lock:
            for drive in self.drives:
                drive.torque_permille = 0
        if self._on_sync in self.network.subscribers.get(SYNC_COB_ID, []):
            self.network.unsubscribe(SYNC_COB_ID, self._on_sync)
        for drive in self.drives:
            if self.network.nodes.get(drive.id) is drive:  # started
                del self.network[drive.id]  # remove_network: heartbeat stops, PDOs unsubscribed
