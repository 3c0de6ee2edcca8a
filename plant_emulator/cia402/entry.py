"""``hil emulator --profile cia402``: two emulated CiA 402 drives on the CAN bus.

:mod:`plant_emulator.entry` dispatches here after reading the configuration. The drives are
canopen LocalNodes (:class:`~plant_emulator.cia402.rig.Cia402Rig`) on a :class:`canopen.Network`
over the bus of ``--can`` (default ``transport.can``); the node ids and object-dictionary values
come from ``[cia402]``. The run is always paced by the controller's SYNC (each SYNC steps the
world one control period); ``--lockstep`` (or ``controller.clock = lockstep``) only widens the
SYNC-loss limit to ``cia402.lockstep_sync_timeout_s``, since a lockstep controller may pause
over a tick. Unless ``--no-vision-link``, the camera pose after each SYNC goes out on zenoh for
the vision process (with ``camera.model = "image"`` the emulated camera renders and streams
frames from them, unless ``--no-camera``), and the harness's scenario resets are taken from
``hil/sim/control``, as with the emulated DSP.
SIGTERM / SIGINT or ``--duration`` (simulated seconds in lockstep, wall seconds in realtime) end
it with exit status 0; ``--json`` prints the final counters.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import threading
import time
from typing import TYPE_CHECKING, Any

from hal import cia402_od as cia
from hal import strict_json

if TYPE_CHECKING:
    from hal.config import RigConfig
    from plant_emulator.cia402.drive import EmulatedDrive
    from plant_emulator.cia402.rig import Cia402Rig, StepListener
    from plant_emulator.pose_link import PoseLink
    from plant_emulator.world import World

WAIT_SLICE_S = 0.05
"""How often the main thread looks at the stop flag and the simulated time."""


def _after_sync(poses: PoseLink) -> StepListener:
    """After each SYNC: the stepped world's camera pose, stamped with the SYNC's arrival (when
    the arm was there, which the features' age counts from)."""

    def step(syncs: int, world: World, stamp_ns: int) -> None:
        poses(syncs, round(world.t * 1e9), world.pose(), True, stamp_ns)

    return step


def _config(args: argparse.Namespace) -> RigConfig:
    """The configuration, its ``hardware.profile`` the one served (so what the cia402 profile
    refuses, a rate 0x60C2 cannot carry, is refused before anything opens); the rig key only
    when poses go out (CANopen frames carry no MAC)."""
    from hal.config import load_config
    from hal.secoc import configure_key

    cfg = load_config(args.config).with_overrides({"hardware.profile": "cia402"})
    return configure_key(cfg, args.key_file, "hil emulator") if args.vision_link else cfg


def serve_cia402(args: argparse.Namespace, stop: threading.Event) -> int:
    """Serve the drives until ``stop`` or ``args.duration``; returns the exit status."""
    import canopen

    from hal.bus import open_bus, process_spec
    from plant_emulator.cia402.rig import Cia402Rig
    from plant_emulator.entry import callback_errors_text, with_callback_errors, zenoh_where_of

    cfg = _config(args)

    spec = args.can or cfg.transport.can
    where = str(process_spec(spec))  # HalConfigError: malformed, or in-process only
    poses: PoseLink | None = None
    with contextlib.ExitStack() as stack:
        bus = stack.enter_context(open_bus(spec, bitrate=cfg.cia402.bitrate, fd=False))
        zenoh_where = ""
        session = None
        if args.vision_link:
            from hal.secoc import rig_key
            from hal.zenoh_session import open_session
            from plant_emulator.pose_link import PoseLink, PosePublisher

            session = stack.enter_context(
                open_session(
                    cfg, listen=True, endpoint=args.zenoh_endpoint, config_file=args.zenoh_config
                )
            )
            publisher = PosePublisher(session, key=rig_key(cfg))
            stack.callback(publisher.close)
            poses = PoseLink(publisher)
            zenoh_where = f", camera poses on zenoh {zenoh_where_of(session)}"
            if args.camera and cfg.camera.model == "image":
                from plant_emulator.camera_link import start_camera

                poses.camera, _frames = start_camera(cfg, session, stack, rig_key(cfg))
                zenoh_where += f", camera frames {cfg.camera.width_px}x{cfg.camera.height_px}"
        network = canopen.Network(bus)
        network.connect()  # the notifier on our bus (closed by open_bus's context)
        stack.callback(network.notifier.stop)
        lockstep = bool(args.lockstep) or cfg.controller.clock == "lockstep"
        new_run = None if poses is None else poses.new_run
        on_step = None if poses is None else _after_sync(poses)
        rig = Cia402Rig(cfg, network, on_step=on_step, lockstep=lockstep, on_reset=new_run)
        stack.callback(rig.close)
        for drive in rig.drives:
            drive.on_fault = _say_fault
        if session is not None:
            from plant_emulator.entry import serve_sim_control

            stack.enter_context(serve_sim_control(session, rig, rig_key(cfg)))
        rig.start()
        ids = ", ".join(str(d.id) for d in rig.drives)
        print(
            f"hil emulator: serving CiA 402 drives (nodes {ids}) on {where} "
            f"(paced by SYNC{', lockstep' if lockstep else ''}){zenoh_where}",
            file=sys.stderr,
            flush=True,
        )
        t0 = time.monotonic()
        while not stop.wait(WAIT_SLICE_S):
            if args.duration and _elapsed(rig, t0, lockstep) >= args.duration:
                break
        wall_s = time.monotonic() - t0
        summary = with_callback_errors(_summary(rig, where, wall_s, poses), session)
    if args.json:
        print(strict_json.dumps(summary), flush=True)
    else:
        states = ", ".join(f"node {d['node_id']} {d['state']}" for d in summary["drives"])
        print(
            f"hil emulator: {summary['sim_time_s']:.3f} s simulated in {wall_s:.3f} s, "
            f"{summary['syncs']} SYNCs; {states}{callback_errors_text(summary)}",
            flush=True,
        )
    return 0


def _elapsed(rig: Cia402Rig, t0: float, lockstep: bool) -> float:
    """Seconds ``--duration`` counts: simulated in lockstep (the world waits for the
    controller), wall in realtime (as the DSP profile's; the world's clock holds while no
    drive is enabled, so it alone would never end a run without a master)."""
    return rig.world.t if lockstep else time.monotonic() - t0


_FAULTS = {
    cia.EMCY_SYNC: "SYNC loss",
    cia.EMCY_HEARTBEAT: "controller heartbeat lost",
    cia.EMCY_PARAMETER: "0x60C2 is not the control period",
    cia.EMCY_POSITION_LIMIT: "joint beyond its position limit",
    cia.EMCY_VELOCITY_LIMIT: "joint beyond its velocity limit",
}


def _say_fault(node_id: int, code: int) -> None:
    """A drive's fault on stderr the moment it happens (as the DSP emulator says its own)."""
    what = _FAULTS.get(code, "fault")
    print(
        f"hil emulator: fault: node {node_id} EMCY 0x{code:04X} ({what})",
        file=sys.stderr,
        flush=True,
    )


def _summary(rig: Cia402Rig, where: str, wall_s: float, poses: PoseLink | None) -> dict[str, Any]:
    with rig.lock:
        return {
            "transport": where,
            "mode": "cia402",
            "syncs": rig.syncs,
            "sim_time_s": rig.world.t,
            "wall_time_s": wall_s,
            "q": [float(v) for v in rig.world.q],
            "dq": [float(v) for v in rig.world.dq],
            "drives": [
                {
                    "node_id": d.id,
                    "state": d.power.state.name,
                    "nmt": d.nmt.state,
                    "emcys": [f"0x{code:04X}" for code in d.emcys],
                    "rejected_rpdos": d.pdos.rejected_rpdos,
                    "torque_off": _torque_off(d),
                }
                for d in rig.drives
            ],
            "poses_published": 0 if poses is None else poses.publisher.published,
            "pose_errors": 0 if poses is None else poses.errors,
            "camera": None
            if poses is None or poses.camera is None
            else poses.camera.stats.as_dict(),
        }


def _torque_off(drive: EmulatedDrive) -> dict[str, Any] | None:
    """The drive's last fault: EMCY code, what it means, and how long after the last SYNC the
    torque went off (None: no fault)."""
    if drive.torque_off is None:
        return None
    code, _at, since_s = drive.torque_off
    return {
        "emcy": f"0x{code:04X}",
        "reason": _FAULTS.get(code, "fault"),
        "after_last_sync_ms": None if since_s is None else since_s * 1e3,
    }
