"""The emulated CiA 402 drives on an in-process python-can virtual bus, with a master network.

:func:`drives_on_virtual_bus` starts :class:`plant_emulator.cia402.rig.Cia402Rig` on its own
virtual channel and yields it with a second, independent :class:`canopen.Network` on the same
channel for the test's master (canopen's RemoteNode / BaseNode402 from the shipped EDS). The
frames on one channel are handled in the order they were sent, so an SDO answered after an
RPDO was sent proves that the RPDO was handled first.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import can
import canopen

from hal.cia402_od import EDS_PATH
from hal.config import RigConfig
from plant_emulator.cia402.drive import EmulatedDrive
from plant_emulator.cia402.rig import Cia402Rig

_channels = itertools.count()
REPLY_TIMEOUT_S = 5.0
"""How long a test waits for a frame that the drives send in answer (generous: shared CPUs)."""


class ManualClock:
    """The drives' monitor clock, advanced by the test."""

    def __init__(self, t: float = 100.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


class FakeNow:
    """The master's ``now_ns``, fixed unless the test moves it (``ns``)."""

    def __init__(self) -> None:
        self.ns = 10**12

    def __call__(self) -> int:
        return self.ns


@dataclass
class Bench:
    rig: Cia402Rig
    master: canopen.Network
    clock: ManualClock | None

    def remote(self, node_id: int, cls: type = canopen.RemoteNode) -> canopen.RemoteNode:
        """A master-side node of the shipped EDS, its SDO timeout generous."""
        node = cls(node_id, str(EDS_PATH))
        self.master.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = REPLY_TIMEOUT_S
        return node

    def drive(self, node_id: int) -> EmulatedDrive:
        """The emulated drive itself, to read what its object dictionary holds without the bus.

        A test that checks what a master under test wrote reads here, not by SDO: the
        test's SDO client shares the node's SDO COB-IDs with that master, and its network
        thread may hand it a late copy of the master's last answer ("Unexpected response
        0x60" under load)."""
        return next(d for d in self.rig.drives if d.id == node_id)


@contextmanager
def drives_on_virtual_bus(
    cfg: RigConfig | None = None, *, manual_clock: bool = True, lockstep: bool = False
) -> Iterator[Bench]:
    """The rig (monitor thread off with the manual clock: the test polls) and a master."""
    channel = f"cia402-{os.getpid()}-{next(_channels)}"
    cfg = cfg or RigConfig()
    clock = ManualClock() if manual_clock else None
    emulator = canopen.Network(can.Bus(interface="virtual", channel=channel))
    emulator.connect()
    master = canopen.Network(can.Bus(interface="virtual", channel=channel))
    master.connect()
    kwargs = {"clock": clock} if clock is not None else {}
    rig = Cia402Rig(cfg, emulator, lockstep=lockstep, **kwargs)
    try:
        rig.start(monitor=clock is None)
        yield Bench(rig, master, clock)
    finally:
        rig.close()
        for node_id in list(master.nodes):
            del master[node_id]
        master.disconnect()
        emulator.disconnect()


def sync_and_wait(bench: Bench, *tpdos: canopen.pdo.PdoMap) -> None:
    """Send one SYNC and wait until each of ``tpdos`` arrived (the drives handled the SYNC)."""
    for pdo in tpdos:
        pdo.is_received = False
    bench.master.sync.transmit()
    for pdo in tpdos:
        with pdo.receive_condition:
            if not pdo.is_received:
                pdo.receive_condition.wait(REPLY_TIMEOUT_S)
        assert pdo.is_received, f"no {pdo.name} after SYNC"


def round_trip(node: canopen.RemoteNode) -> int:
    """One SDO read of the statusword: every frame sent before it has been handled."""
    return node.sdo[0x6041].raw
