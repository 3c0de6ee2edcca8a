"""``hil simulate``: the in-process closed loop (emulator physics + controller, no transports)."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from hal.arguments import bounded_int, duration
from rt_controller.commands.common import (
    add_config_option,
    add_law_options,
    add_scenario_options,
    add_set_option,
    config_from_args,
    refuse_rhc_options_off_law,
)
from rt_controller.commands.interrupts import run_interruptible
from rt_controller.commands.progress import Progress, add_quiet_option

if TYPE_CHECKING:
    from hal.config import RigConfig
    from rt_controller.control.simulate import SimResult


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate",
        help="run the closed loop in-process, faster than real time",
        description="Closed loop of the emulator's arm physics and the controller's law, "
        "without transports. Torque is held between ticks; J = sum of l(x_k, u_k) / rate.",
    )
    add_law_options(p)
    add_scenario_options(p)
    add_config_option(p)
    add_set_option(p)
    p.add_argument(
        "--duration", type=duration(), default=6.0, metavar="S", help="seconds (default 6)"
    )
    for flag, what in (("--state-delay", "joint state"), ("--feature-delay", "image features")):
        p.add_argument(
            flag,
            type=bounded_int(0, 1000, what="periods"),
            default=0,
            metavar="N",
            help=f"the law sees the {what} of N control periods ago (default 0)",
        )
    p.add_argument(
        "--no-predict",
        action="store_true",
        help="do not compensate the ages of state and features (controller.predict_state and "
        "predict_features = false)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    add_quiet_option(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from rt_controller.commands.output import print_summary
    from rt_controller.control.simulate import tick_count, too_short
    from rt_controller.errors import ControllerConfigError

    cfg = config_from_args(args)
    refuse_rhc_options_off_law(args, cfg)  # the law of a simulation does not change
    rate = cfg.rates.control_hz
    ticks = tick_count(args.duration, rate)
    if ticks < 1:  # before numba compiles anything
        raise ControllerConfigError(too_short(args.duration, rate))
    for flag, delay in (
        ("--state-delay", args.state_delay),
        ("--feature-delay", args.feature_delay),
    ):
        if delay and delay >= ticks - 1:  # tick k sees sample max(0, k - delay)
            raise ControllerConfigError(
                f"{flag} {delay} periods leaves the law nothing but the first sample in a "
                f"{ticks}-tick run (--duration {args.duration:g} s at {rate:g} Hz): use a longer "
                "--duration or a shorter delay"
            )
    progress = Progress.of(args, "hil simulate")

    def body() -> int:
        result = _closed_loop(args, cfg, progress)
        print_summary(result.as_dict(), args.json, f"hil simulate --law {result.law}")
        return 0

    return run_interruptible("hil simulate", body, lambda: "no result")


def _closed_loop(args: argparse.Namespace, cfg: RigConfig, progress: Progress) -> SimResult:
    ctl = cfg.controller
    with progress.stage(
        f"preparing the {ctl.law} law and the arm model (numba compiles its kernels on a cold "
        "cache, a minute or two)"
    ):
        from plant_emulator.world import World
        from rt_controller.control.controller import Controller
        from rt_controller.control.simulate import run_closed_loop

        world, controller = World(cfg), Controller(cfg)
    with progress.stage(
        f"running {args.duration:g} s of closed loop ({ctl.law} at {cfg.rates.control_hz:g} Hz)"
    ):
        return run_closed_loop(
            world,
            controller,
            cfg,
            args.duration,
            args.state_delay,
            predict=ctl.predict_state and ctl.predict_features and not args.no_predict,
            feature_delay=args.feature_delay,
        )
