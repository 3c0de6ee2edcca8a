"""The PDO service canopen's LocalNode leaves out: synchronous RPDOs latched at SYNC, TPDOs
sent on SYNC, and the CiA 301 rules for changing a PDO's COB-ID or mapping.

canopen's ``LocalNode`` keeps the PDO objects (0x1400.., 0x1600.., 0x1800.., 0x1A00..) in its
object dictionary and its :class:`canopen.pdo.PdoMap` encodes and decodes the frames, but it
neither applies a received RPDO nor sends a TPDO on SYNC (its maintainers say so in its issues).
:class:`PdoService` does both for one node, using canopen's maps for every byte:

* an RPDO frame is only kept when it arrives; :meth:`PdoService.latch` (at the SYNC) writes the
  newest one of each RPDO into the object dictionary, so a value that arrives between SYNCs
  takes effect at the next SYNC, never earlier;
* :meth:`PdoService.transmit` fills each enabled TPDO from the object dictionary and sends it
  (transmission types 1..240 every n-th SYNC; 0, 254 and 255 on every SYNC);
* :meth:`PdoService.check_write` refuses, with the CiA 301 SDO abort codes, a mapping change
  while the PDO is enabled (0x08000022), a mapping entry written while sub-index 0 is not 0
  (0x08000022), a COB-ID change of an enabled PDO (0x06090030), a mapping of an object that
  does not exist or cannot be mapped in that direction (0x06040041) or one longer than 64 bits
  (0x06040042).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import TYPE_CHECKING

from canopen.objectdictionary import ODVariable
from canopen.pdo import PdoMap
from canopen.sdo import SdoAbortedError

from hal.cia402_od import MAP_ENTRIES, PDO_DISABLED, RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP

if TYPE_CHECKING:
    from canopen import LocalNode

ABORT_DEVICE_STATE = 0x08000022
"""Data cannot be transferred or stored because of the present device state."""
ABORT_VALUE_RANGE = 0x06090030
"""Value range of parameter exceeded."""
ABORT_NOT_MAPPABLE = 0x06040041
"""Object cannot be mapped to the PDO."""
ABORT_PDO_LENGTH = 0x06040042
"""The number and length of the objects to be mapped would exceed the PDO length."""

EMCY_PDO_LENGTH = 0x8210
"""CiA 301 EMCY: PDO not processed due to length error."""

_U32 = struct.Struct("<I")
_U8 = struct.Struct("<B")


def _pdo_of(index: int) -> tuple[str, int, int] | None:
    """(kind, comm index, map index) of a PDO object index, or None."""
    for kind, comm, mapping in (("rpdo", RPDO_COMM, RPDO_MAP), ("tpdo", TPDO_COMM, TPDO_MAP)):
        if comm <= index < comm + 0x200:
            return kind, index, mapping + index - comm
        if mapping <= index < mapping + 0x200:
            return kind, comm + index - mapping, index
    return None


class PdoService:
    """The PDOs of one :class:`canopen.LocalNode`; ``emcy(code)`` reports a bad RPDO."""

    def __init__(self, node: LocalNode, emcy: Callable[[int], None]) -> None:
        self.node = node
        self._emcy = emcy
        self._maps: dict[int, PdoMap] = {}
        for kind, pdo in (("rpdo", node.rpdo), ("tpdo", node.tpdo)):
            base = RPDO_COMM if kind == "rpdo" else TPDO_COMM
            for n, pdo_map in pdo.map.items():
                self._maps[base + n - 1] = pdo_map
        self._pending: dict[int, bytes] = {}
        self._subscribed: dict[int, PdoMap] = {}
        self._last_sent: dict[int, bytes] = {}
        self.rejected_rpdos = 0
        """RPDO frames of the wrong length (not applied, EMCY 0x8210) and mapped values the
        object refused (that value not applied; the frame's other values are)."""

    # -- configuration --------------------------------------------------------------------
    def reload(self) -> None:
        """Read every PDO's configuration from the object dictionary and subscribe the RPDOs."""
        for comm in self._maps:
            self._load(comm)
        self._resubscribe()

    def _u32(self, index: int, subindex: int) -> int:
        return _U32.unpack(self.node.get_data(index, subindex))[0]

    def _u8(self, index: int, subindex: int) -> int:
        return _U8.unpack(self.node.get_data(index, subindex))[0]

    def _load(self, comm: int) -> None:
        pdo_map = self._maps[comm]
        mapping = _pdo_of(comm)[2]
        cob_id = self._u32(comm, 1)
        pdo_map.cob_id = cob_id & 0x1FFFFFFF
        pdo_map.enabled = not cob_id & PDO_DISABLED
        pdo_map.trans_type = self._u8(comm, 2)
        pdo_map.clear()
        for sub in range(1, self._u8(mapping, 0) + 1):
            entry = self._u32(mapping, sub)
            pdo_map.add_variable(entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF)

    def _resubscribe(self) -> None:
        network = self.node.network
        wanted = {
            m.cob_id: m for c, m in self._maps.items() if c < TPDO_COMM and m.enabled and m.map
        }
        for cob_id in list(self._subscribed):
            if cob_id not in wanted:
                network.unsubscribe(cob_id, self._on_rpdo)
                del self._subscribed[cob_id]
        for cob_id, pdo_map in wanted.items():
            if cob_id not in self._subscribed:
                network.subscribe(cob_id, self._on_rpdo)
            self._subscribed[cob_id] = pdo_map
        self._pending = {c: d for c, d in self._pending.items() if c in self._subscribed}

    def close(self) -> None:
        """Stop receiving RPDOs."""
        for cob_id in list(self._subscribed):
            self.node.network.unsubscribe(cob_id, self._on_rpdo)
        self._subscribed.clear()
        self._pending.clear()

    def check_write(self, index: int, subindex: int, data: bytes) -> None:
        """Refuse (``SdoAbortedError``) a write the PDO rules forbid; others pass."""
        pdo = _pdo_of(index)
        if pdo is None:
            return
        _kind, comm, mapping = pdo
        if comm not in self._maps:
            return  # not one of our PDOs: the object dictionary answers "no such object"
        enabled = not self._u32(comm, 1) & PDO_DISABLED
        if index == comm:
            if subindex == 1 and enabled:
                new = _U32.unpack(data)[0]
                if not new & PDO_DISABLED and new & 0x1FFFFFFF != self._u32(comm, 1) & 0x1FFFFFFF:
                    raise SdoAbortedError(ABORT_VALUE_RANGE)
            return
        if enabled:
            raise SdoAbortedError(ABORT_DEVICE_STATE)
        if subindex == 0:
            self._check_mapping(pdo[0], mapping, _U8.unpack(data)[0])
        elif self._u8(mapping, 0) != 0:
            raise SdoAbortedError(ABORT_DEVICE_STATE)

    def _check_mapping(self, kind: str, mapping: int, count: int) -> None:
        if count > MAP_ENTRIES:
            raise SdoAbortedError(ABORT_PDO_LENGTH)
        bits = 0
        for sub in range(1, count + 1):
            entry = self._u32(mapping, sub)
            var = self._mapped_variable(entry >> 16, (entry >> 8) & 0xFF)
            readable = var is not None and (var.writable if kind == "rpdo" else var.readable)
            if not (readable and var.pdo_mappable and len(var) == entry & 0xFF):
                raise SdoAbortedError(ABORT_NOT_MAPPABLE)
            bits += entry & 0xFF
        if bits > 64:
            raise SdoAbortedError(ABORT_PDO_LENGTH)

    def _mapped_variable(self, index: int, subindex: int) -> ODVariable | None:
        od = self.node.object_dictionary
        if index not in od:
            return None
        obj = od[index]
        if isinstance(obj, ODVariable):
            return obj if subindex == 0 else None
        return obj.subindices.get(subindex)  # not obj[...]: an ODArray invents any sub-index

    def after_write(self, index: int) -> None:
        """A PDO object changed: reload that PDO (and its subscription)."""
        pdo = _pdo_of(index)
        if pdo is not None and pdo[1] in self._maps:
            self._load(pdo[1])
            self._resubscribe()

    # -- the SYNC ---------------------------------------------------------------------------
    def _on_rpdo(self, can_id: int, data: bytearray, _timestamp: float) -> None:
        """Keep the newest frame of the RPDO; it is applied at the next SYNC."""
        self._pending[can_id] = bytes(data)

    def latch(self, operational: bool) -> None:
        """At SYNC: write the newest RPDO of each kind into the object dictionary (through the
        node's write callbacks). Frames that arrived outside OPERATIONAL are dropped."""
        pending, self._pending = self._pending, {}
        if not operational:
            return
        for cob_id, data in pending.items():
            pdo_map = self._subscribed.get(cob_id)
            if pdo_map is None:
                continue
            if len(data) < len(pdo_map.data):
                self.rejected_rpdos += 1
                self._emcy(EMCY_PDO_LENGTH)
                continue
            pdo_map.data = bytearray(data)
            for var in pdo_map.map:
                try:
                    self.node.set_data(var.index, var.subindex, var.get_data())
                except SdoAbortedError:  # a value the object refuses (e.g. mode 4): counted
                    self.rejected_rpdos += 1

    def transmit(self, sync_count: int) -> int:
        """At SYNC (after the latch): send the TPDOs due; returns how many were sent."""
        sent = 0
        for comm, pdo_map in self._maps.items():
            if comm < TPDO_COMM or not pdo_map.enabled or not pdo_map.map:
                continue
            kind = pdo_map.trans_type
            if 1 <= kind <= 240 and sync_count % kind:
                continue
            if 241 <= kind <= 253:
                continue  # reserved / RTR-only types: never on SYNC
            for var in pdo_map.map:
                var.set_data(self.node.get_data(var.index, var.subindex))
            data = bytes(pdo_map.data)
            if kind == 0 and self._last_sent.get(comm) == data:
                continue  # acyclic synchronous: only when the values changed
            self._last_sent[comm] = data
            pdo_map.transmit()
            sent += 1
        return sent
