"""python-can's ``udp_multicast`` transport, pinned to the loopback interface.

python-can's own :class:`can.interfaces.udp_multicast.UdpMulticastBus` binds to every interface,
joins the group on the interface of the default route and defaults to IPv6 with hop limit 1, so
frames may reach the LAN and the bus fails to open on hosts without a route (user-mode Linux, a
network namespace with only ``lo``). This bus keeps python-can's wire format (msgpack-packed
``can.Message``, :func:`~can.interfaces.udp_multicast.utils.pack_message`) but:

* sends through ``lo`` only (``IP_MULTICAST_IF`` = 127.0.0.1, or the ``lo`` index for IPv6), with
  a multicast TTL / hop limit of 0 by default: frames never leave the host;
* joins the group on ``lo`` only and binds to the group address, so other groups and ports on
  the host are not received (``IP_MULTICAST_ALL`` off);
* sends from its own socket, so it can tell its own frames apart and honour
  ``receive_own_messages`` (python-can's bus cannot).

IPv4 group ``239.74.163.2`` (python-can's ``DEFAULT_GROUP_IPv4``) is the default because
environments without IPv6 exist (user-mode Linux has none). An IPv6 ``ff..`` group works where
the host routes IPv6 multicast through ``lo``; where it does not (by default Linux gives ``lo`` no
``MULTICAST`` flag and puts the only ``ff00::/8`` route on the LAN interface) the bus refuses to
open with :class:`GroupUnreachableError` instead of opening and then failing every send.

What the bus checks and counts, so that nothing is lost silently:

* ``send()`` refuses a frame that a receiver would discard (11-bit id above 0x7FF, 29-bit id
  above 0x1FFFFFFF, more than 8 data bytes on classic CAN or 64 on CAN FD, a CAN FD length that
  has no DLC, DLC/data mismatch, ...) with :class:`InvalidFrameError`; nothing is sent;
* a receive buffer smaller than asked (the kernel caps ``SO_RCVBUF`` at ``net.core.rmem_max``)
  gives a :class:`ReceiveBufferWarning` at open;
* datagrams the kernel dropped because the receive buffer was full are counted in
  :attr:`LoopbackMulticastBus.kernel_drops` (``SO_RXQ_OVFL``); datagrams on the group that are
  not python-can messages in :attr:`LoopbackMulticastBus.malformed_datagrams`.

The bus is also a python-can plugin: register ``hal.udp_loopback:LoopbackMulticastBus`` under the
``can.interface`` entry point (``scripts/can_peer_suite.py`` does so to run python-can's own
back-to-back suite against it).
"""

from __future__ import annotations

import contextlib
import ipaddress
import logging
import os
import select
import socket
import struct
import sys
import time
import warnings
from typing import Any

import can
from can.interfaces.udp_multicast.utils import (
    is_msgpack_installed,
    pack_message,
    unpack_message,
)

from hal.errors import HalCodecError, HalTransportError

log = logging.getLogger(__name__)

DEFAULT_GROUP = "239.74.163.2"
DEFAULT_PORT = 43113
_IP_MULTICAST_ALL = getattr(socket, "IP_MULTICAST_ALL", 49)  # Linux value; absent in Python
_MAX_DATAGRAM = 4096
RCVBUF_BYTES = 4 * 1024 * 1024
"""Receive buffer asked for by default (the kernel caps it at net.core.rmem_max)."""
_SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)  # Linux value; absent in Python
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux value; absent in Python
_TIMESPEC = struct.Struct("@qq")
_CMSG_SPACE = (
    socket.CMSG_SPACE(4) + socket.CMSG_SPACE(_TIMESPEC.size) if hasattr(socket, "CMSG_SPACE") else 0
)
_LINUX = sys.platform.startswith("linux")
CAN_FD_LENGTHS = frozenset((*range(9), 12, 16, 20, 24, 32, 48, 64))
"""Payload lengths a CAN FD frame can carry (DLC 0..15)."""
RMEM_MAX = "/proc/sys/net/core/rmem_max"
LOOP_PROBE_TIMEOUT_S = 2.0
"""How long open waits for its probe datagram to come back through lo (a refusal waits this)."""


class GroupUnreachableError(HalTransportError, can.CanInitializationError):
    """The multicast group cannot be sent to through ``lo`` (refused at open, one line)."""

    error_code = None


class InvalidFrameError(HalCodecError, can.CanOperationError):
    """``send()`` was given a frame that no receiver would accept; it was not sent."""

    error_code = None


class ReceiveBufferWarning(RuntimeWarning):
    """The kernel granted a smaller receive buffer than the bus asked for."""


def frame_problem(msg: can.Message, fd: bool = True) -> str | None:
    """Why ``msg`` is not a valid CAN frame on a bus with(out) CAN FD, or ``None`` if it is.

    The rules are those of the wire (and of :meth:`can.Message._check`, which every receiver of
    the python-can ``udp_multicast`` format applies): a frame that breaks one is discarded by
    the receiver, so the sender must refuse it.
    """
    arb = msg.arbitration_id
    if not isinstance(arb, int) or isinstance(arb, bool) or arb < 0:
        return f"arbitration id {arb!r} is not a non-negative integer"
    if msg.is_extended_id and arb > 0x1FFFFFFF:
        return f"29-bit arbitration id 0x{arb:X} is above 0x1FFFFFFF"
    if not msg.is_extended_id and arb > 0x7FF:
        return f"11-bit arbitration id 0x{arb:X} is above 0x7FF (set is_extended_id for 29 bits)"
    if msg.is_fd and not fd:
        return "a CAN FD frame on a bus opened with fd=False"
    length = len(msg.data) if msg.data is not None else 0
    if msg.is_remote_frame:
        if msg.is_fd:
            return "CAN FD has no remote frames"
        if msg.is_error_frame:
            return "a frame cannot be a remote and an error frame at once"
        if length:
            return "a remote frame carries no data"
        if not 0 <= msg.dlc <= 8:
            return f"remote frame DLC {msg.dlc} is not in 0..8"
    elif msg.dlc != length:
        return f"DLC {msg.dlc} does not match the {length} data bytes"
    if msg.is_fd:
        if length > 64:
            return f"{length} data bytes: a CAN FD frame carries at most 64"
        if length not in CAN_FD_LENGTHS:
            return (
                f"{length} data bytes: no CAN FD DLC has this length "
                "(0..8, 12, 16, 20, 24, 32, 48, 64)"
            )
    else:
        if length > 8:
            return f"{length} data bytes: a classic CAN frame carries at most 8 (set is_fd)"
        if msg.bitrate_switch or msg.error_state_indicator:
            return "bitrate switch / error state indicator exist on CAN FD frames only"
    return None


def _rmem_max() -> str:
    try:
        with open(RMEM_MAX, encoding="ascii") as fh:
            return fh.read().strip()
    except OSError:
        return "unknown"


class LoopbackMulticastBus(can.BusABC):
    """A host-local virtual CAN bus between processes over UDP multicast on ``lo``.

    :param channel: multicast group (IPv4 ``224.0.0.0/4`` or IPv6 ``ff00::/8``).
    :param port: UDP port; different ports are different buses.
    :param hop_limit: multicast TTL / hop limit; 0 (the default) keeps datagrams on the host.
    :param receive_own_messages: also receive the frames this bus sent.
    :param fd: accept and send CAN FD frames.
    :param rcvbuf: receive buffer to ask the kernel for, in bytes (``SO_RCVBUF``); a smaller
        grant gives a :class:`ReceiveBufferWarning`.
    :raises GroupUnreachableError: the group cannot be sent to through ``lo``.
    """

    def __init__(
        self,
        channel: str = DEFAULT_GROUP,
        port: int = DEFAULT_PORT,
        hop_limit: int = 0,
        receive_own_messages: bool = False,
        fd: bool = True,
        rcvbuf: int = RCVBUF_BYTES,
        **kwargs: Any,
    ) -> None:
        is_msgpack_installed()
        try:
            group = ipaddress.ip_address(str(channel))
        except ValueError as exc:
            raise can.CanInitializationError(f"{channel!r} is not an IP address") from exc
        if not group.is_multicast:
            raise can.CanInitializationError(f"{channel} is not a multicast address")
        if not 0 <= int(port) <= 65535 or not 0 <= int(hop_limit) <= 255:
            raise can.CanInitializationError(f"bad port {port} or hop limit {hop_limit}")
        if int(rcvbuf) <= 0:
            raise can.CanInitializationError(f"bad receive buffer size {rcvbuf}")
        super().__init__(channel=str(channel), **kwargs)
        self._group = str(group)
        self._port = int(port)
        self._receive_own = receive_own_messages
        self._can_protocol = can.CanProtocol.CAN_FD if fd else can.CanProtocol.CAN_20
        self.malformed_datagrams = 0
        """Datagrams on the group that were not python-can messages (skipped, not raised)."""
        self._kernel_drops = 0
        self.rcvbuf_asked = int(rcvbuf)
        """Receive buffer asked for (bytes)."""
        self.rcvbuf_granted = 0
        """Receive buffer the kernel granted, in the same unit as asked (bytes)."""
        self._rx: socket.socket | None = None
        self._tx: socket.socket | None = None
        self._dest: tuple[Any, ...] = (self._group, self._port)
        try:
            self._open(int(hop_limit))
            self._check_route(int(hop_limit))
        except BaseException as exc:
            self._close_sockets()
            self._is_shutdown = True
            if isinstance(exc, OSError) and not isinstance(exc, HalTransportError):
                raise can.CanInitializationError(
                    f"cannot open UDP multicast {self._group}:{self._port} on loopback: {exc}"
                ) from exc
            raise
        self._own = self._tx.getsockname()[:2] if self._tx else None
        self.channel_info = (
            f"udp_multicast {self._group} port {self._port} on loopback (hop limit {hop_limit})"
        )
        self._check_rcvbuf()

    @property
    def kernel_drops(self) -> int:
        """Datagrams for this bus that the kernel dropped because the receive buffer was full.

        From ``SO_RXQ_OVFL``: the kernel reports the count with the next datagram it queues, so
        drops show up once a later frame has been received.
        """
        return self._kernel_drops

    @property
    def sender(self) -> socket.socket | None:
        """The sending socket (None once shut down): its multicast TTL and interface are what
        keeps the bus on this host."""
        return self._tx

    # ---------------------------------------------------------------------------- sockets

    def _setup_rx(self, rx: socket.socket) -> None:
        rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if hasattr(socket, "SO_REUSEPORT"):
            rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        with contextlib.suppress(OSError):  # the grant is checked in _check_rcvbuf
            rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.rcvbuf_asked)
        granted = rx.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        # Linux doubles the value asked for (the other half is its bookkeeping) and reports it.
        self.rcvbuf_granted = granted // 2 if _LINUX else granted
        try:
            rx.setsockopt(socket.SOL_SOCKET, _SO_RXQ_OVFL, 1)
        except OSError as exc:  # pragma: no cover - not Linux
            log.debug("SO_RXQ_OVFL unavailable, kernel drops are not counted: %s", exc)
        try:  # receive stamps from the kernel, as SocketCAN gives them
            rx.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        except OSError as exc:  # pragma: no cover - not Linux
            log.debug("SO_TIMESTAMPNS unavailable, frames are stamped when read: %s", exc)

    def _v6(self) -> bool:
        return ":" in self._group

    def _join(self, rx: socket.socket, port: int) -> None:
        """Bind ``rx`` to the group on ``port`` and join the group on ``lo`` only."""
        if self._v6():
            lo_index = socket.if_nametoindex("lo")
            rx.bind((self._group, port, 0, lo_index))
            mreq = socket.inet_pton(socket.AF_INET6, self._group) + lo_index.to_bytes(4, "little")
            rx.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_JOIN_GROUP, mreq)
        else:
            rx.bind((self._group, port))
            lo = socket.inet_aton("127.0.0.1")
            mreq = socket.inet_aton(self._group) + lo
            rx.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
            with contextlib.suppress(OSError):  # not Linux: binding to the group filters already
                rx.setsockopt(socket.IPPROTO_IP, _IP_MULTICAST_ALL, 0)

    def _sender(self, hop_limit: int) -> socket.socket:
        """A socket that sends to the group through ``lo`` only, with ``hop_limit``."""
        if self._v6():
            tx = socket.socket(socket.AF_INET6, socket.SOCK_DGRAM)
            try:
                tx.setsockopt(
                    socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_IF, socket.if_nametoindex("lo")
                )
                tx.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_HOPS, hop_limit)
                tx.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_LOOP, 1)
                tx.bind(("::1", 0))
            except BaseException:
                tx.close()
                raise
            return tx
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
            tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, hop_limit)
            tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
            tx.bind(("127.0.0.1", 0))
        except BaseException:
            tx.close()
            raise
        return tx

    def _dest_for(self, port: int) -> tuple[Any, ...]:
        if self._v6():
            return (self._group, port, 0, socket.if_nametoindex("lo"))
        return (self._group, port)

    def _open(self, hop_limit: int) -> None:
        family = socket.AF_INET6 if self._v6() else socket.AF_INET
        rx = self._rx = socket.socket(family, socket.SOCK_DGRAM)
        self._setup_rx(rx)
        self._join(rx, self._port)
        self._tx = self._sender(hop_limit)
        self._dest = self._dest_for(self._port)

    def _refusal(self, what: str) -> GroupUnreachableError:
        if self._v6():
            hint = (
                "lo does not carry IPv6 multicast here (Linux gives lo no MULTICAST flag and "
                "routes ff00::/8 to the LAN interface); use an IPv4 group such as "
                f"udp_multicast:{DEFAULT_GROUP}:{self._port}"
            )
        else:
            hint = "check that lo is up and routes 224.0.0.0/4, or use --can socketcan:vcan0"
        family = "IPv6" if self._v6() else "IPv4"
        return GroupUnreachableError(
            f"cannot use {family} multicast group {self._group} port {self._port} on lo: "
            f"{what}; {hint}"
        )

    def _check_route(self, hop_limit: int) -> None:
        """Refuse a group whose datagrams would not reach the buses on this host.

        First ``connect()`` of the sending socket: the kernel looks the route up as a send
        would, without sending (sends then use the connected socket). Then one datagram is
        sent, with the bus's own options, to the group on a private port that only a probe
        socket of this bus listens on, and must come back: a host may route the group and
        still not deliver it (IPv6 with hop limit 0 on ``lo``). The peers on the bus's port
        see nothing of it.
        """
        if self._tx is None:  # pragma: no cover - _open sets it or raises
            raise can.CanInitializationError("the sending socket is not open")
        try:
            self._tx.connect(self._dest)
        except OSError as exc:
            raise self._refusal(f"no route ({exc.strerror or exc})") from exc
        family = socket.AF_INET6 if self._v6() else socket.AF_INET
        nonce = os.urandom(16)
        with socket.socket(family, socket.SOCK_DGRAM) as probe:
            self._join(probe, 0)  # an ephemeral port of its own, bound without reuse
            probe_port = probe.getsockname()[1]
            with self._sender(hop_limit) as tx:
                try:
                    tx.sendto(nonce, self._dest_for(probe_port))
                except OSError as exc:
                    raise self._refusal(f"send failed ({exc.strerror or exc})") from exc
            deadline = time.monotonic() + LOOP_PROBE_TIMEOUT_S
            while (left := deadline - time.monotonic()) > 0:
                if select.select([probe], [], [], left)[0] and probe.recv(64) == nonce:
                    return
        raise self._refusal(
            f"a datagram sent to the group did not come back within {LOOP_PROBE_TIMEOUT_S} s"
        )

    def _check_rcvbuf(self) -> None:
        if self.rcvbuf_granted < self.rcvbuf_asked:
            warnings.warn(
                f"UDP multicast bus {self._group}:{self._port}: the kernel granted a "
                f"{self.rcvbuf_granted}-byte receive buffer, {self.rcvbuf_asked} asked "
                f"(net.core.rmem_max = {_rmem_max()}); a burst beyond it is dropped and "
                f"counted in kernel_drops; raise the cap with: "
                f"sudo sysctl -w net.core.rmem_max={self.rcvbuf_asked}",
                ReceiveBufferWarning,
                stacklevel=3,
            )

    def _close_sockets(self) -> None:
        for sock in (self._rx, self._tx):
            if sock is not None:
                try:
                    sock.close()
                except OSError as exc:  # pragma: no cover - close of a UDP socket
                    log.warning("closing UDP socket: %s", exc)

    # ------------------------------------------------------------------------- python-can

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        rx = self._rx
        if rx is None or self._is_shutdown:
            raise can.CanOperationError("the bus is shut down")
        while True:
            try:
                ready, _, _ = select.select([rx], [], [], timeout)
                if not ready:
                    return None, False
                data, ancdata, flags, sender = rx.recvmsg(_MAX_DATAGRAM, _CMSG_SPACE)
            except (OSError, ValueError) as exc:
                raise can.CanOperationError(f"UDP multicast receive failed: {exc}") from exc
            stamp = None
            for level, kind, payload in ancdata:
                if level != socket.SOL_SOCKET:
                    continue
                if kind == _SO_RXQ_OVFL and len(payload) >= 4:
                    self._kernel_drops = int.from_bytes(payload[:4], sys.byteorder)
                elif kind == _SO_TIMESTAMPNS and len(payload) >= _TIMESPEC.size:
                    sec, nsec = _TIMESPEC.unpack_from(payload)
                    stamp = sec + nsec * 1e-9
            if self._receive_own or sender[:2] != self._own:
                break
            # Our own frame: skip it and look at what else is already queued, so that a
            # non-blocking drain (timeout=0) is not stopped by our own traffic.
            timeout = 0.0
        try:
            if flags & socket.MSG_TRUNC:
                raise ValueError(f"datagram longer than {_MAX_DATAGRAM} bytes")
            arrival = time.time() if stamp is None else stamp
            msg = unpack_message(data, replace={"timestamp": arrival}, check=True)
        except Exception as exc:  # garbage on the group must not break the reader
            self.malformed_datagrams += 1
            log.debug("skipping a datagram that is not a CAN message: %s", exc)
            return None, False
        if msg.is_fd and self._can_protocol is not can.CanProtocol.CAN_FD:
            return None, False
        return msg, False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send ``msg`` to every bus on the group (never blocks on loopback).

        :raises InvalidFrameError: ``msg`` is not a valid frame for this bus (nothing is sent).
        :raises can.CanOperationError: the bus is shut down or the kernel refused the datagram.
        """
        tx = self._tx
        if tx is None or self._is_shutdown:
            raise can.CanOperationError("the bus is shut down")
        problem = frame_problem(msg, fd=self._can_protocol is can.CanProtocol.CAN_FD)
        if problem is not None:
            raise InvalidFrameError(f"not sent: {problem}")
        try:
            packed = pack_message(msg)
        except (TypeError, ValueError) as exc:  # e.g. a channel msgpack cannot pack
            raise InvalidFrameError(f"not sent: cannot pack the frame: {exc}") from exc
        try:
            tx.send(packed)
        except OSError as exc:
            raise can.CanOperationError(f"UDP multicast send failed: {exc}") from exc

    def fileno(self) -> int:
        return self._rx.fileno() if self._rx is not None else -1

    def shutdown(self) -> None:
        """Close both sockets; safe to call twice."""
        if self._is_shutdown:
            return
        super().shutdown()
        self._close_sockets()
