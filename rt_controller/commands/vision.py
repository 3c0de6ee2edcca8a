"""``hil vision``: dispatches to the emulator's vision process (plant_emulator.vision_cli)."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    from plant_emulator import vision_cli

    p = sub.add_parser(
        "vision",
        help="run the vision process: camera model -> features on zenoh hil/vision/features",
        description="Computes the image features f of the scenario's target from the camera "
        "pose the emulator publishes, adds noise/frame rate/latency, publishes on zenoh.",
    )
    vision_cli.add_arguments(p)
    p.set_defaults(handler=vision_cli.run_from_args)
