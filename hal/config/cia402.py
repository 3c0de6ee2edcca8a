"""The ``[cia402]`` section: the CANopen CiA 402 drives of the ``cia402`` hardware profile.

Both sides read it: the emulated drives (``hil emulator --profile cia402``) take their node ids
and object-dictionary values from it, and the controller's master finds the drives by these node
ids, each described by its EDS (``eds_1``, ``eds_2``: the vendor's file of a real drive; the
units it then reads from the drives themselves, by SDO)."""

from __future__ import annotations

from dataclasses import dataclass

from hal.config.values import Vec2

CONTROLLER_NODE_ID = 0x7F
"""The controller's own CANopen node id (its heartbeat's COB-ID is 0x700 + it, and the
drives' heartbeat consumer 0x1016 watches it): no drive may have it."""


@dataclass(frozen=True)
class Cia402Config:
    """CiA 402 drives (one per joint) on the CAN bus."""

    node_id_1: int = 1
    """CANopen node id of joint 1's drive (1..126; 127 is the controller's)."""
    node_id_2: int = 2
    """CANopen node id of joint 2's drive (1..126; 127 is the controller's)."""
    eds_1: str = ""
    """Path of the EDS of joint 1's drive, as its vendor ships it (empty: the shipped
    ``hal/cia402_drive.eds``, the emulated drive's). Relative to the working directory of the
    command, like ``transport.key_file``. Checked when the configuration loads: canopen must
    read it, and it must hold every object the master maps, reads or writes
    (:data:`hal.cia402_master.eds.REQUIRED_OBJECTS`). The emulated drives ignore it."""
    eds_2: str = ""
    """Path of the EDS of joint 2's drive (as ``eds_1``)."""
    bitrate: int = 1_000_000
    """CAN bit rate of the drives' bus, bit/s: given to python-can when the cia402 profile opens
    the bus, so adapters that set their rate (PCAN, Kvaser, ...) run at it; a SocketCAN
    interface has the rate ``ip link`` gave it (the error for a missing one names this rate in
    the line that brings it up); virtual and udp_multicast buses ignore it."""
    rated_torque: Vec2 = (10.0, 1.0)
    """Emulated drives: motor rated torque per joint, Nm (object 0x6076; the unit of the target
    and actual torque is its per mille, so INT16 reaches 32.767 times it: keep it above
    ``robot.tau_max`` / 32.767)."""
    encoder_increments: int = 1_048_576
    """Emulated drives: position increments per revolution (object 0x608F; 20 bits)."""
    sync_loss_periods: float = 2.5
    """Emulated drives: no SYNC for this many cycle periods (0x1006, else 0x60C2) in NMT
    OPERATIONAL is a SYNC loss: torque off, FAULT, EMCY 0x8700 (2.5 puts it within 3 periods)."""
    lockstep_sync_timeout_s: float = 2.0
    """Emulated drives, lockstep (``controller.clock = lockstep`` or ``--lockstep``): no SYNC for
    this many seconds is a SYNC loss instead (the controller paces the world and may take longer
    than a period over a tick; the heartbeat consumer still catches a dead controller)."""
