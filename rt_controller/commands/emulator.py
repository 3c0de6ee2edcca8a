"""``hil emulator``: dispatches to the emulated DSP node (plant_emulator.entry)."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    from plant_emulator.entry import add_emulator_arguments

    p = sub.add_parser(
        "emulator",
        help="serve the arm: emulated DSP on CAN (physics 1 kHz, encoders, watchdog, Sync)",
        description="The plant emulator's DSP node: arm physics at 1 kHz, the latest valid "
        "TorqueCommand applied (saturated), quantised joint state and DspStatus on CAN, a "
        "watchdog, and in --lockstep one Sync per control period. Publishes the camera pose "
        "on zenoh for `hil vision` unless --no-vision-link. SIGTERM/SIGINT: torque off, exit 0.",
    )
    add_emulator_arguments(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from plant_emulator.entry import run_emulator

    return run_emulator(args)
