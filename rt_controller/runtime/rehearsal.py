"""Realtime: rehearse the last tick shortly before each release (``controller.rehearse``), so
the code the tick runs is warm in the caches when the release comes. After a period of sleep
on a shared VM the first run of that code is several times slower; the rehearsal pays that
instead of the tick. Nothing of it is kept:

- read: the observation is judged as the tick judges it, without following the drive state
  (the DSP's statuses stay for the tick);
- decide: the last tick's rule call on a second controller whose result is thrown away (the
  run's controller and its warm-started solver are untouched);
- write: the last torque through :meth:`hal.joint_client.JointClient.rehearse_torque` (a shadow
  codec; nothing reaches the bus, the real counters do not move).
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
        decision_fields(self.controller, d)
        loop.hw.dsp.rehearse_torque(
            float(d.tau[0]), float(d.tau[1]), release_delay_us=loop.last_write_delay_us
        )
        loop.counters.rehearsals += 1
