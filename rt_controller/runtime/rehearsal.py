"""Realtime: rehearse the last tick shortly before each release (``controller.rehearse``), so
its code is warm when the release comes (after a sleep on a shared VM its first run is several
times slower). Nothing of it is kept: the inputs are judged without following the drive state,
the last rule call runs on a second controller, and the last torque goes through
:meth:`hal.joint_client.JointClient.rehearse_torque` (nothing reaches the bus).
"""

from __future__ import annotations

from hal.config import RigConfig
from rt_controller.control.controller import Controller, warm_up
from rt_controller.runtime.cycle_record import decision_fields
from rt_controller.runtime.loop import ControlLoop, apply_rule

MIN_PERIOD_NS = 5_000_000
"""Rehearse only at this period or longer (faster ticks keep their code warm)."""


class Rehearsal:
    """The second controller and the replay of ``loop``'s last tick."""

    def __init__(self, cfg: RigConfig, loop: ControlLoop) -> None:
        self.loop = loop
        self.controller = Controller(cfg)
        warm_up(self.controller, cfg)

    @staticmethod
    def wanted(cfg: RigConfig) -> bool:
        """Whether ``cfg`` asks for it and its period is long enough to go cold."""
        return cfg.controller.rehearse and cfg.rates.control_period_ns >= MIN_PERIOD_NS

    def __call__(self) -> None:
        loop = self.loop
        call = loop.last_call
        if call is None:
            return
        loop.observe(loop.clock.now_ns(), loop.drive.mode)
        d = apply_rule(self.controller, call)
        loop.hw.dsp.rehearse_torque(*d.torque, release_delay_us=loop.last_write_delay_us)
        decision_fields(self.controller, d)
        loop.counters.rehearsals += 1
