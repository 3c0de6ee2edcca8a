"""The DSP profile of the hardware seam (:class:`hal.hardware_interface.HardwareInterface`):
the emulated or real DSP of ``hal/hil.dbc`` over CAN, the image features over zenoh.

The CAN link is a :class:`~hal.joint_client.JointClient` in poll mode (read in the control
thread, no receive thread); the features come through a
:class:`~rt_controller.runtime.feature_link.FeatureLink` (the zenoh half every profile shares).
The drive's state is followed by :class:`DrivePolicy`. In lockstep the DSP paces:
:meth:`DspHardware.step` waits for its ``Sync(k)``.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from hal.errors import HalTimeoutError
from hal.hardware_interface import InputJudge, Observation, StopFlag
from hal.joint_client import JointClient
from hal.vision_receivers import FeatureDecoder
from rt_controller.errors import ControllerError
from rt_controller.runtime import diagnostics
from rt_controller.runtime.context import RunContext
from rt_controller.runtime.drive_policy import ENABLE_TIMEOUT_S, DrivePolicy
from rt_controller.runtime.feature_link import FeatureLink
from rt_controller.runtime.pacers import LOCKSTEP_FEATURE_TIMEOUT_S

STARTUP_TIMEOUT_S = 20.0
"""How long start-up waits for the first joint state and features before giving up."""
ARMING_COMMANDS = 8
"""Realtime: zero torques sent while arming, at least: the DSP learns the cycle's phase from the
earliest of its recent commands, so a slow first law frame does not place the scenario's t = 0
late (which would delay every torque of the run by as much)."""
PREFETCH_GUARD_NS = 1_000_000
"""Realtime: the read-ahead between releases stops this long before the next release."""


class DspHardware:
    """CAN and zenoh of one run, read and written from the control thread."""

    def __init__(
        self,
        ctx: RunContext,
        dsp: JointClient,
        session: Any,
        features: FeatureDecoder,
        *,
        lockstep: bool,
        record_raw: bool,
    ) -> None:
        """``session``: the run's zenoh session (``subscribe``, ``subscribe_ring``);
        ``lockstep``: the DSP's Sync paces (features by callback, no cyclic arming)."""
        self.ctx = ctx
        self.dsp = dsp
        self.features = FeatureLink(
            ctx, session, features, by_callback=lockstep, record_raw=record_raw
        )
        self.lockstep = lockstep
        self.record_raw = record_raw
        self.drive = DrivePolicy(ctx)
        self.can_base = dsp.stats.e2e.as_dict()
        """The CAN receive counters when this run began (a plan's links outlive its runs)."""
        self._enable_by: int | None = None
        """Arming: when the DSP must report *operation enabled* (None: not yet activated)."""
        self._arming_sent = 0
        self._states_seen = -1
        self._last_sync: int | None = None
        self.last_tau = (0.0, 0.0)

    # --- lifecycle --------------------------------------------------------------------------
    def configure(self, stop: StopFlag) -> None:
        """Subscribe this run to the features (and the camera's images, when logged), hook
        the raw CAN log, then wait for the DSP's first joint state (and, read by ring, the
        first features)."""
        self._attach()
        self._wait_ready(stop, features=not self.lockstep)

    def activate(self, now_ns: int) -> bool:
        """ENABLE on the first call, then (realtime) a zero torque (Enable = 0) at every call,
        until the DSP reports *operation enabled* and has had ``ARMING_COMMANDS`` of them. The
        command stream is cyclic from ENABLE on (the DSP arms its watchdog there); the zeros
        teach the DSP the cycle's phase, on which the emulated DSP places the scenario's t = 0
        when the first law tick's frame applies torque. Counted in ``arming_ticks``."""
        clock, dsp = self.ctx.clock, self.dsp
        expired = self._enable_by is not None and clock.now_ns() > self._enable_by
        self._poll(clock.now_ns())
        needed = 0 if self.lockstep else ARMING_COMMANDS
        if self.drive.enabled_now(dsp, expired) and self._arming_sent >= needed:
            return True
        if self._enable_by is None:
            dsp.enable()
            self._enable_by = clock.now_ns() + round(ENABLE_TIMEOUT_S * 1e9)
        if not self.lockstep:
            delay = (clock.now_ns() - now_ns) // 1000
            dsp.send_torque(0.0, 0.0, release_delay_us=delay, enable=False)
            self._arming_sent += 1
            self.ctx.counters.arming_ticks += 1
        self._states_seen = dsp.states_received
        return False

    def deactivate(self) -> None:
        """Zero torque and DISABLE when armed; end the feeds and hooks of this run."""
        if self._enable_by is not None:
            self.dsp.send_torque(0.0, 0.0)
            self.dsp.disable()
            self._enable_by = None
        self.features.detach()
        self.dsp.frame_hook = self.dsp.tx_hook = None

    # --- pacing -----------------------------------------------------------------------------
    def wait_inputs(self, until_ns: int) -> None:
        """Realtime, between releases: block on the CAN socket and decode what arrives, so the
        tick finds it decoded; no decode starts within ``PREFETCH_GUARD_NS`` (at most a
        quarter period) of ``until_ns``."""
        now = self.ctx.clock.now_ns()
        guard_ns = min(PREFETCH_GUARD_NS, self.ctx.cfg.rates.control_period_ns // 4)
        stop_ns = until_ns - guard_ns
        if now >= stop_ns:
            time.sleep(max(0, until_ns - now) / 1e9)
        elif self.dsp.wait_readable((stop_ns - now) / 1e9):
            self._poll(self.ctx.clock.now_ns())

    def step(self, timeout_s: float) -> int | None:
        """Lockstep: the next new ``Sync(k)`` of the DSP (a re-sent one, whose command was
        lost, gets the last torque again), then the features answering pose k; k, or None
        when no Sync came within ``timeout_s``."""
        while True:
            try:
                k = self.dsp.wait_sync(timeout_s)
            except HalTimeoutError:
                return None
            last = self._last_sync
            if last is None or k > last:
                break
            if k == last:  # a re-sent Sync: our command was lost, send it again
                self.dsp.send_torque(*self.last_tau, tick=k)
        self._last_sync = k
        self.features.wait_pose(k, LOCKSTEP_FEATURE_TIMEOUT_S)
        return k

    # --- read and write ---------------------------------------------------------------------
    def read(self, now_ns: int, judge: InputJudge) -> Observation:
        """Everything waiting on the links taken off, the drive state followed to ``now_ns``,
        the newest joint state and features judged stale or fresh by ``judge``."""
        self._poll(self.ctx.clock.now_ns())  # stamped when actually read, not at the wake-up
        dsp = self.dsp
        state_new = dsp.states_received != self._states_seen
        self._states_seen = dsp.states_received
        mode = self.drive.follow(dsp, now_ns, judge.status_limit_s)
        state_stale, state_ns = False, None
        try:
            state = dsp.latest_state(max_age_s=judge.state_limit_s, now_ns=now_ns)
            q, dq, state_ns = np.array(state.q), np.array(state.dq), state.t_ns
            state_age_ms = (now_ns - state.t_ns) / 1e6
        except HalTimeoutError:
            state_stale, q, dq, state_age_ms = True, np.full(2, math.nan), np.zeros(2), math.nan
        f, f_age_ms, f_stale, f_valid = self.features.latest(now_ns, judge)
        return Observation(
            q=q,
            dq=dq,
            f=f,
            state_ns=state_ns,
            state_age_ms=state_age_ms,
            state_stale=state_stale,
            f_age_ms=f_age_ms,
            f_stale=f_stale,
            f_valid=f_valid,
            drive_mode=mode,
            state_new=state_new,
        )

    def write(self, tau: tuple[float, float], *, sync: int | None, release_ns: int) -> None:
        """Send the tick's torque: answering Sync ``sync`` when given, else carrying how long
        after its release it left (realtime, ``TorqueCommand.Tick``)."""
        t1, t2 = self.last_tau = tau
        if sync is not None:
            self.dsp.send_torque(t1, t2, tick=sync)
        else:
            delay = (self.ctx.clock.now_ns() - release_ns) // 1000
            self.dsp.send_torque(t1, t2, release_delay_us=delay)

    def command(self, action: str) -> str | None:
        """An operator's ``arm``, ``disarm`` or ``mark`` (:meth:`DrivePolicy.operate`)."""
        return self.drive.operate(self.dsp, action)

    def diagnostics(self) -> dict[str, dict[str, Any]]:
        """The receive verdicts of this run (``can_rx``, ``features``) and the drive (``dsp``)."""
        return {
            "can_rx": diagnostics.since(self.can_base, self.dsp.stats.e2e.as_dict()),
            "features": self.features.features.counts.as_dict(),
            "dsp": self.drive.block(self.dsp),
        }

    # --- links ------------------------------------------------------------------------------
    def _attach(self) -> None:
        """This run's feature subscriptions, and the raw CAN log's hooks."""
        self.features.attach()
        if self.record_raw:
            rec, now = self.ctx.recorder, self.ctx.clock.now_ns
            self.dsp.frame_hook = lambda m: rec.record_can(m, now(), "rx")
            self.dsp.tx_hook = lambda m: rec.record_can(m, now(), "tx")

    def _wait_ready(self, stop: StopFlag, *, features: bool) -> None:
        """Until the first joint state (and, with ``features``, image features)."""
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not stop.is_set():
            self._poll(self.ctx.clock.now_ns())
            have_state = self.dsp.state_age_s() is not None
            if have_state and (not features or self.features.features.latest is not None):
                return
            if time.monotonic() > deadline:
                missing = "joint state (CAN)" if not have_state else "image features (zenoh)"
                raise ControllerError(
                    f"no {missing} within {STARTUP_TIMEOUT_S:.0f} s: is `hil emulator` "
                    f"(and `hil vision`) running on the same transports?"
                )
            self.ctx.pause(10_000_000)

    def _poll(self, now_ns: int) -> None:
        """Take every CAN frame waiting on the bus and the newest feature messages off the
        transports, into their decoders (stamped ``now_ns`` where the clock has no kernel
        stamps)."""
        self.dsp.drain(now_ns, timestamps=self.ctx.clock.kernel_stamps)
        self.features.poll(now_ns)


__all__ = ["STARTUP_TIMEOUT_S", "DspHardware"]
