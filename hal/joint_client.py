"""Controller-side joint I/O client: the rt_controller's only door to the DSP.

The client has no thread of its own: the caller's thread reads the bus (the controller's control
thread, as part of the tick, so no other Python thread runs in the control process).
:meth:`JointClient.drain` takes every frame waiting without blocking, :meth:`JointClient.wait_sync`
reads until the DSP's next lockstep Sync, :meth:`JointClient.await_new_session` until the DSP
confirms a new scenario; :meth:`JointClient.wait_readable` blocks until a frame waits. Each frame
goes through :class:`~hal.can_codec.ControllerCodec` (E2E and SecOC check, DBC decode) and
updates the latest joint state, DspStatus (and the backlog of :meth:`JointClient.take_statuses`)
and Sync tick. One thread uses a client at a time.

Typical use::

    with JointClient.open("auto", cfg) as dsp:
        dsp.enable()                               # FAULT_RESET + ENABLE
        tick = dsp.wait_sync(timeout=1.0)          # lockstep: reads the bus up to the Sync
        # realtime instead: dsp.wait_readable(...) until the release, then dsp.drain()
        state = dsp.latest_state()                 # HalTimeoutError when the DSP went silent
        dsp.send_torque(tau[0], tau[1], tick=tick)

``close()`` (idempotent) disarms the DSP if this client armed it and shuts down a bus it owns.
"""

from __future__ import annotations

import collections
import logging
import select
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import can

from hal.can_codec import ControllerCodec, DspCommand
from hal.can_frames import (
    RELEASE_DELAY_SATURATED,
    DspStatus,
    JointPosition,
    JointState,
    JointVelocity,
    Sync,
)
from hal.can_tap import FrameTap
from hal.config import RigConfig
from hal.drive_state import DriveState
from hal.e2e import DEFAULT_REINIT_AFTER_NS, E2EStats
from hal.errors import HalError, HalTimeoutError, HalTransportError
from hal.resources import release, track
from hal.secoc import rig_key

log = logging.getLogger(__name__)

STATUS_BACKLOG = 64
"""DspStatus frames kept for :meth:`JointClient.take_statuses` between two calls (the DSP sends
10 a second plus one per change)."""
FOREIGN_STAMP_S = 3600.0
"""A receive stamp this far from the wall clock is on another clock (PCAN without the
``uptime`` package stamps from boot): taken as no stamp, so the frame is judged on arrival."""
DRAIN_MAX_FRAMES = 1024
"""Most frames one :meth:`JointClient.drain` takes (half a second of free-running state at
1 kHz): a bus that never runs dry (a flood, or a reader slower than the sender) ends the drain
here instead of never, and the rest waits for the next one."""


@dataclass
class ClientStats:
    """Receive-side counters of a :class:`JointClient`."""

    e2e: E2EStats = field(default_factory=E2EStats)
    """Verdict of every frame received (accepted, ignored and each kind of rejection)."""
    frames: int = 0
    """Frames taken off the bus."""
    states: int = 0
    """Complete joint states assembled (JointPosition + JointVelocity of one sample)."""
    syncs: int = 0
    statuses: int = 0
    transport_errors: int = 0
    """Receive calls that raised (a driver error), counted and read as "no frame"."""
    drains_cut: int = 0
    """Drains that stopped at ``DRAIN_MAX_FRAMES`` frames (the bus had not run dry)."""
    foreign_stamps: int = 0
    """Frames whose receive stamp was not on the wall clock, judged on arrival instead."""


class JointClient:
    """Latest joint state, DSP status and Sync tick; torque and enable/disable commands.

    :param bus: an open python-can bus (see :func:`hal.bus.open_bus`); the client reads and
        writes it through a :class:`~hal.can_tap.FrameTap` (:attr:`bus`), whose hooks show
        every raw frame, e.g. to the run's log.
    :param cfg: rig configuration (``controller.state_timeout_s`` is the default staleness limit).
    :param owns_bus: shut ``bus`` down on :meth:`close`.
    :param key: the rig key (default: ``cfg.transport.key_file``, loaded and checked, else this
        process's ephemeral key; see :mod:`hal.secoc`).
    """

    def __init__(
        self,
        bus: can.BusABC,
        cfg: RigConfig | None = None,
        *,
        owns_bus: bool = False,
        reinit_after_s: float | None = DEFAULT_REINIT_AFTER_NS * 1e-9,
        key: bytes | None = None,
    ) -> None:
        self.cfg = cfg if cfg is not None else RigConfig()
        self.bus = FrameTap(bus)
        self._owns_bus = owns_bus
        self._key = key if key is not None else rig_key(self.cfg)
        self._codec = ControllerCodec(reinit_after_s=reinit_after_s, key=self._key)
        self._closed = False
        self._armed = False
        # receive-side state, written by process_frame
        self._pos: JointPosition | None = None
        self._vel: JointVelocity | None = None
        self._state: JointState | None = None
        self._status: DspStatus | None = None
        self._status_t_ns = 0
        self._new_statuses: collections.deque[DspStatus] = collections.deque(maxlen=STATUS_BACKLOG)
        self._sync_tick: int | None = None
        self._sync_seq = 0
        self._sync_seen = 0
        self._n = ClientStats()
        """The receive counters (``e2e`` aside: the codec keeps those)."""
        track(self, f"JointClient({bus.channel_info})")

    @classmethod
    def open(
        cls, spec: str | None = None, cfg: RigConfig | None = None, **kwargs: Any
    ) -> JointClient:
        """Open the bus of ``spec`` (default: ``cfg.transport.can``) and own it."""
        from hal.bus import open_bus  # local: keeps the client importable without transports

        rig = cfg if cfg is not None else RigConfig()
        bus = open_bus(spec if spec is not None else rig.transport.can)
        try:
            return cls(bus, rig, owns_bus=True, **kwargs)
        except BaseException:
            bus.shutdown()
            raise

    # ------------------------------------------------------------------------- lifecycle

    def close(self) -> None:
        """Disarm the DSP if this client armed it, release an owned bus."""
        if self._closed:
            return
        if self._armed:
            try:
                self.disable()
            except HalError as exc:
                log.warning("could not disarm the DSP on close: %s", exc)
        self._closed = True
        if self._owns_bus:
            self.bus.shutdown()
        release(self)

    def __enter__(self) -> JointClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        return self._closed

    # ------------------------------------------------------------------------------ send

    def _send(self, make: Callable[[ControllerCodec], can.Message]) -> None:
        if self._closed:
            raise HalError("JointClient is closed")
        msg = make(self._codec)
        try:
            self.bus.send(msg, timeout=0.05)
        except (can.CanError, OSError) as exc:
            where = self.bus.channel_info
            raise HalTransportError(f"CAN send on {where} failed: {exc}") from exc

    def send_torque(
        self,
        tau1: float,
        tau2: float,
        *,
        tick: int | None = None,
        release_delay_us: int | None = None,
        enable: bool | None = None,
    ) -> None:
        """Send a TorqueCommand (counter + CRC); ``tick`` defaults to the latest Sync tick.

        Realtime callers pass ``release_delay_us`` instead: how long after the controller's
        release this command leaves, carried in ``Tick`` (saturated at 65535), so the DSP learns
        the controller's cycle from its releases, not from when commands arrive. The Enable bit
        follows :meth:`enable`/:meth:`disable`; ``enable=False`` keeps the command stream cyclic
        without applying torque (arming). :class:`~hal.errors.HalCodecError` for NaN/inf,
        :class:`HalTransportError` when the bus refuses the frame.
        """
        if release_delay_us is not None:
            tick = min(max(0, int(release_delay_us)), RELEASE_DELAY_SATURATED)
        elif tick is None:
            tick = self._sync_tick or 0
        on = self._armed if enable is None else enable and self._armed
        self._send(lambda c: c.encode_torque(tau1, tau2, enable=on, tick=tick))

    def enable(self, *, reset_fault: bool = True) -> None:
        """Arm the DSP: DspControl ENABLE (drive state -> OPERATION_ENABLED), after a
        FAULT_RESET with ``reset_fault`` (so a DSP in FAULT is armed too; without, ENABLE is
        refused there). Each command goes twice with consecutive counters, so a receiver that
        resynchronises on the first still accepts the second."""
        self._armed = True
        if reset_fault:
            self.send_command(DspCommand.FAULT_RESET)
        self.send_command(DspCommand.ENABLE)

    def send_command(self, command: DspCommand, *, repeat: int = 2) -> None:
        """Send one DspControl ``command`` ``repeat`` times (consecutive counters)."""
        cmd = DspCommand(command)
        for _ in range(repeat):
            self._send(lambda c: c.encode_control(cmd))

    def disable(self) -> None:
        """Remove torque: DspControl DISABLE (twice) and a zero TorqueCommand with Enable=0."""
        self._armed = False
        self.send_command(DspCommand.DISABLE)
        self.send_torque(0.0, 0.0, enable=False)

    def await_new_session(self, timeout_s: float, request: Callable[[], object]) -> DspStatus:
        """Call ``request`` (which asks an emulated lockstep DSP for a scenario reset, e.g. on
        the simulator-control channel, :mod:`hal.sim_control`), then read the bus until the
        DspStatus of the DSP's new session (Tick 0, switch-on disabled) arrives, and return
        it; every input received before it is forgotten. :class:`HalTimeoutError` when no such
        status comes within ``timeout_s`` (a realtime or real DSP is not rewound).
        """
        old = None if self._status is None else self._status.session
        request()
        deadline = time.monotonic() + timeout_s
        while (remaining := deadline - time.monotonic()) > 0:
            msg = self._receive(min(remaining, 0.05))
            if msg is None:
                continue
            before = self._n.statuses
            self.process_frame(msg)
            st = self._status
            if (
                self._n.statuses != before
                and st is not None
                and st.session != old
                and st.tick == 0
                and st.drive_state is DriveState.SWITCH_ON_DISABLED
            ):
                self._pos = self._vel = self._state = None
                self._sync_tick = None
                self._sync_seen = self._sync_seq
                self._new_statuses.clear()
                self._new_statuses.append(st)
                return st
        raise HalTimeoutError(
            f"the DSP on {self.bus.channel_info} did not confirm a scenario reset within "
            f"{timeout_s:g} s (only an emulated DSP in lockstep resets)"
        )

    # --------------------------------------------------------------------------- receive

    def _receive(self, timeout_s: float) -> can.Message | None:
        """The next frame off the bus within ``timeout_s`` (0: only one already waiting), else
        None. A driver error reads as None: it is counted (``transport_errors``) and logged on
        the first and every 1000th, and never reaches the caller."""
        try:
            msg = self.bus.recv(timeout=timeout_s)
            if msg is not None and msg.timestamp:
                self._foreign_stamp(msg)
            return msg
        except Exception as exc:  # driver errors must not reach the tick
            self._n.transport_errors += 1
            if self._n.transport_errors == 1 or self._n.transport_errors % 1000 == 0:
                log.warning("CAN receive error on %s: %s", self.bus.channel_info, exc)
            return None

    def _foreign_stamp(self, msg: can.Message) -> None:
        """Clear a receive stamp that is not on the wall clock (counted, said once)."""
        if abs(msg.timestamp - time.time()) <= FOREIGN_STAMP_S:
            return
        msg.timestamp = 0.0
        self._n.foreign_stamps += 1
        if self._n.foreign_stamps == 1:
            log.warning(
                "CAN receive stamps on %s are not on the wall clock (PCAN without the uptime "
                "package?): frames are judged on arrival instead",
                self.bus.channel_info,
            )

    def drain(self, now_ns: int | None = None, *, timestamps: bool = False) -> int:
        """Read and decode every frame waiting on the bus, without blocking; how many. A frame's
        receive time is ``now_ns`` (default: now) or, with ``timestamps``, the bus's receive
        stamp moved to the monotonic clock and capped at ``now_ns``. Never raises for a bad
        frame or a driver error (both counted; a driver error ends the drain). At most
        ``DRAIN_MAX_FRAMES`` frames: a bus that never runs dry cannot hold the caller."""
        now = time.monotonic_ns() if now_ns is None else now_ns
        wall_minus_mono = time.time_ns() - time.monotonic_ns() if timestamps else 0
        for n in range(DRAIN_MAX_FRAMES):
            msg = self._receive(0.0)
            if msg is None:
                return n
            t = now
            if timestamps and msg.timestamp:
                t = min(now, round(msg.timestamp * 1e9) - wall_minus_mono)
            self.process_frame(msg, t)
        self._n.drains_cut += 1
        return DRAIN_MAX_FRAMES

    def process_frame(self, msg: can.Message, t_ns: int | None = None) -> None:
        """The receive path of every frame read: E2E check, decode, update. Never raises."""
        now = time.monotonic_ns() if t_ns is None else t_ns
        self._n.frames += 1
        frame = self._codec.decode(msg, now)
        if frame is None:
            return
        if isinstance(frame, JointPosition):
            self._pos = frame
            self._pair(now)
        elif isinstance(frame, JointVelocity):
            self._vel = frame
            self._pair(now)
        elif isinstance(frame, DspStatus):
            self._status, self._status_t_ns = frame, now
            self._new_statuses.append(frame)
            self._n.statuses += 1
        elif isinstance(frame, Sync):
            self._sync_tick = frame.tick
            self._sync_seq += 1
            self._n.syncs += 1

    def _pair(self, now: int) -> None:
        pos, vel = self._pos, self._vel
        if pos is None or vel is None or pos.sample != vel.sample:
            return
        self._state = JointState((pos.q1, pos.q2), (vel.dq1, vel.dq2), pos.sample, now)
        self._pos = self._vel = None
        self._n.states += 1

    # ----------------------------------------------------------------------------- read

    def latest_state(self, max_age_s: float | None = None, now_ns: int | None = None) -> JointState:
        """The newest joint state; :class:`HalTimeoutError` when none is newer than
        ``max_age_s`` (default ``cfg.controller.state_timeout_s``) at ``now_ns`` (default: now).
        """
        limit = self.cfg.controller.state_timeout_s if max_age_s is None else max_age_s
        state = self._state
        now = time.monotonic_ns() if now_ns is None else now_ns
        if state is None:
            raise HalTimeoutError(
                f"no joint state received from the DSP on {self.bus.channel_info} yet "
                "(is the emulator running on this bus?)"
            )
        age = (now - state.t_ns) * 1e-9
        if age > limit:
            raise HalTimeoutError(
                f"DSP silent: last joint state is {age * 1e3:.1f} ms old "
                f"(limit {limit * 1e3:.1f} ms) on {self.bus.channel_info}"
            )
        return state

    @property
    def states_received(self) -> int:
        """Joint states (position + velocity pairs) received so far."""
        return self._n.states

    def wait_readable(self, timeout_s: float) -> bool:
        """Block until a frame is waiting on the bus (True, nothing read) or ``timeout_s``
        passed. A bus without a file descriptor: one pause of 0.2 ms, then False."""
        if timeout_s <= 0:
            return False
        try:
            fd = self.bus.fileno()
        except (NotImplementedError, AttributeError, OSError):
            fd = -1
        if fd < 0:
            time.sleep(min(timeout_s, 0.0002))
            return False
        try:
            ready, _, _ = select.select([fd], [], [], timeout_s)
        except (OSError, ValueError):
            return False
        return bool(ready)

    def state_age_s(self) -> float | None:
        """Seconds since the latest joint state arrived; ``None`` before the first one."""
        state = self._state
        return None if state is None else state.age_s()

    @property
    def status(self) -> DspStatus | None:
        """The latest DspStatus (``None`` before the first one). To follow the drive state,
        feed a :class:`hal.drive_state.DriveMonitor` every status (:meth:`take_statuses`)."""
        return self._status

    def take_statuses(self) -> list[DspStatus]:
        """Every DspStatus received since the last call, oldest first (at most
        ``STATUS_BACKLOG``: older ones are dropped, the newest always kept)."""
        out = list(self._new_statuses)
        self._new_statuses.clear()
        return out

    def status_age_s_at(self, now_ns: int) -> float | None:
        """Seconds from the latest DspStatus's arrival to ``now_ns``; ``None`` before one."""
        if self._status is None:
            return None
        return (now_ns - self._status_t_ns) * 1e-9

    @property
    def sync_tick(self) -> int | None:
        """The latest Sync tick (``None`` before the first one)."""
        return self._sync_tick

    def wait_sync(self, timeout: float) -> int:
        """Read (and decode) the bus until a Sync arrives that no earlier call returned; its
        tick (the latest of several). :class:`HalTimeoutError` after ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        while self._sync_seq == self._sync_seen:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or self._closed:
                raise HalTimeoutError(
                    f"no Sync from the DSP within {timeout * 1e3:.1f} ms on "
                    f"{self.bus.channel_info} (is the emulator in lockstep mode?)"
                )
            msg = self._receive(remaining)
            if msg is not None:
                self.process_frame(msg)
        self._sync_seen = self._sync_seq
        return int(self._sync_tick or 0)

    @property
    def stats(self) -> ClientStats:
        """A snapshot of the receive counters."""
        return replace(self._n, e2e=self._codec.stats)
