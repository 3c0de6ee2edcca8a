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
environments without IPv6 exist (user-mode Linux has none); an IPv6 ``ff..`` group works too.
"""

from __future__ import annotations

import contextlib
import ipaddress
import logging
import select
import socket
import time
from typing import Any

import can
from can.interfaces.udp_multicast.utils import (
    is_msgpack_installed,
    pack_message,
    unpack_message,
)

log = logging.getLogger(__name__)

DEFAULT_GROUP = "239.74.163.2"
DEFAULT_PORT = 43113
_IP_MULTICAST_ALL = getattr(socket, "IP_MULTICAST_ALL", 49)  # Linux value; absent in Python
_MAX_DATAGRAM = 4096
RCVBUF_BYTES = 4 * 1024 * 1024
"""Receive buffer asked for (the kernel caps it at net.core.rmem_max)."""


class LoopbackMulticastBus(can.BusABC):
    """A host-local virtual CAN bus between processes over UDP multicast on ``lo``.

    :param channel: multicast group (IPv4 ``224.0.0.0/4`` or IPv6 ``ff00::/8``).
    :param port: UDP port; different ports are different buses.
    :param hop_limit: multicast TTL / hop limit; 0 (the default) keeps datagrams on the host.
    :param receive_own_messages: also receive the frames this bus sent.
    :param fd: accept and send CAN FD frames.
    """

    def __init__(
        self,
        channel: str = DEFAULT_GROUP,
        port: int = DEFAULT_PORT,
        hop_limit: int = 0,
        receive_own_messages: bool = False,
        fd: bool = True,
        **kwargs: Any,
    ) -> None:
        is_msgpack_installed()
        group = ipaddress.ip_address(str(channel))
        if not group.is_multicast:
            raise can.CanInitializationError(f"{channel} is not a multicast address")
        if not 0 <= int(port) <= 65535 or not 0 <= int(hop_limit) <= 255:
            raise can.CanInitializationError(f"bad port {port} or hop limit {hop_limit}")
        super().__init__(channel=str(channel), **kwargs)
        self._group = str(group)
        self._port = int(port)
        self._receive_own = receive_own_messages
        self._can_protocol = can.CanProtocol.CAN_FD if fd else can.CanProtocol.CAN_20
        self.malformed_datagrams = 0
        """Datagrams on the group that were not python-can messages (skipped, not raised)."""
        self._rx: socket.socket | None = None
        self._tx: socket.socket | None = None
        try:
            if group.version == 4:
                self._open_v4(int(hop_limit))
            else:
                self._open_v6(int(hop_limit))
        except OSError as exc:
            self._close_sockets()
            self._is_shutdown = True
            raise can.CanInitializationError(
                f"cannot open UDP multicast {self._group}:{self._port} on loopback: {exc}"
            ) from exc
        self._own = self._tx.getsockname()[:2] if self._tx else None
        self.channel_info = (
            f"udp_multicast {self._group} port {self._port} on loopback (hop limit {hop_limit})"
        )

    # ---------------------------------------------------------------------------- sockets

    def _open_v4(self, hop_limit: int) -> None:
        rx = self._rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if hasattr(socket, "SO_REUSEPORT"):
            rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        with contextlib.suppress(OSError):  # room for bursts of 1 kHz state frames
            rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF_BYTES)
        rx.bind((self._group, self._port))
        lo = socket.inet_aton("127.0.0.1")
        rx.setsockopt(
            socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, socket.inet_aton(self._group) + lo
        )
        with contextlib.suppress(OSError):  # not Linux: binding to the group filters already
            rx.setsockopt(socket.IPPROTO_IP, _IP_MULTICAST_ALL, 0)
        tx = self._tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, lo)
        tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, hop_limit)
        tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        tx.bind(("127.0.0.1", 0))

    def _open_v6(self, hop_limit: int) -> None:
        lo_index = socket.if_nametoindex("lo")
        rx = self._rx = socket.socket(socket.AF_INET6, socket.SOCK_DGRAM)
        rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if hasattr(socket, "SO_REUSEPORT"):
            rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        with contextlib.suppress(OSError):
            rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF_BYTES)
        rx.bind((self._group, self._port, 0, lo_index))
        mreq = socket.inet_pton(socket.AF_INET6, self._group) + lo_index.to_bytes(4, "little")
        rx.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_JOIN_GROUP, mreq)
        tx = self._tx = socket.socket(socket.AF_INET6, socket.SOCK_DGRAM)
        tx.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_IF, lo_index)
        tx.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_HOPS, hop_limit)
        tx.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_LOOP, 1)
        tx.bind(("::1", 0))

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
                data, sender = rx.recvfrom(_MAX_DATAGRAM)
            except (OSError, ValueError) as exc:
                raise can.CanOperationError(f"UDP multicast receive failed: {exc}") from exc
            if self._receive_own or sender[:2] != self._own:
                break
            # Our own frame: skip it and look at what else is already queued, so that a
            # non-blocking drain (timeout=0) is not stopped by our own traffic.
            timeout = 0.0
        try:
            msg = unpack_message(data, replace={"timestamp": time.time()}, check=True)
        except Exception as exc:  # garbage on the group must not break the reader
            self.malformed_datagrams += 1
            log.debug("skipping a datagram that is not a CAN message: %s", exc)
            return None, False
        if msg.is_fd and self._can_protocol is not can.CanProtocol.CAN_FD:
            return None, False
        return msg, False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send ``msg`` to every bus on the group (never blocks on loopback)."""
        tx = self._tx
        if tx is None or self._is_shutdown:
            raise can.CanOperationError("the bus is shut down")
        if msg.is_fd and self._can_protocol is not can.CanProtocol.CAN_FD:
            raise can.CanOperationError("cannot send a CAN FD frame on a bus opened with fd=False")
        try:
            tx.sendto(pack_message(msg), (self._group, self._port))
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
