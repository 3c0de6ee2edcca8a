"""Bus factory: ``INTERFACE[:CHANNEL]`` specs, python-can configuration, the embedded default.

Spec forms (the ``--can`` option and ``transport.can`` of the rig config):

* ``socketcan:vcan0`` (``socketcan`` alone means ``vcan0``), ``socketcan:can0``;
* ``udp_multicast`` = ``udp_multicast:239.74.163.2:43113``; ``udp_multicast:GROUP[:PORT]``,
  ``udp_multicast:[ff15::1]:PORT`` for IPv6. Always host-local (:mod:`hal.udp_loopback`):
  pinned to ``lo`` with ``hop_limit=0`` unless ``hop_limit`` is passed explicitly;
* ``virtual`` (channel ``hil``) or ``virtual:NAME``: python-can's in-process bus (tests and
  in-process tools only: the rig's daemons are separate processes, :func:`process_spec`);
* any other python-can interface name, passed to :class:`can.Bus` as is;
* ``auto`` or ``None``: python-can's own configuration when it names an interface
  (``CAN_INTERFACE``/``CAN_CHANNEL``/``CAN_BITRATE``/``CAN_CONFIG`` or a ``can.conf`` file,
  read with :func:`can.util.load_config`); otherwise ``socketcan:vcan0`` when
  ``/sys/class/net/vcan0`` exists, else ``udp_multicast``.

Every failure to open raises :class:`~hal.errors.HalTransportError` with one line saying what to
do. The returned bus is a context manager and its ``shutdown()`` is safe to call twice.
"""

from __future__ import annotations

import atexit
import configparser
import contextlib
import errno
import ipaddress
import logging
import socket
import threading
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import can.util

from hal.errors import HalConfigError, HalTransportError
from hal.udp_loopback import DEFAULT_GROUP, DEFAULT_PORT, LoopbackMulticastBus

AUTO = "auto"
DEFAULT_VCAN = "vcan0"
DEFAULT_VIRTUAL_CHANNEL = "hil"
SYS_CLASS_NET = Path("/sys/class/net")


def vcan_hint(channel: str = DEFAULT_VCAN) -> str:
    """The shell line that creates and raises a vcan interface."""
    return (
        f"sudo modprobe vcan && sudo ip link add dev {channel} type vcan "
        f"&& sudo ip link set {channel} mtu 72 && sudo ip link set up {channel}"
    )


SOCKETCAN_HINT = f"--can socketcan:{DEFAULT_VCAN} ({vcan_hint()})"
"""The other host-local bus between processes, named in hints when udp_multicast fails."""

NOMINAL_BITRATE = 1_000_000
"""The bus's bit rate when the opener names none (the dsp profile's; the cia402 profile's
openers pass ``cia402.bitrate``)."""
DATA_BITRATE = 2_000_000
"""The CAN FD data-phase bit rate a real interface is brought up with."""


def can_up_hint(channel: str, bitrate: int | None = None, fd: bool = True) -> str:
    """The shell line that brings a real SocketCAN interface up for the rig at ``bitrate``
    (default :data:`NOMINAL_BITRATE`): with CAN FD on for the DSP's 16-byte frames, which
    :func:`open_bus` refuses an interface of MTU 16 for; classic CAN for ``fd=False`` (CANopen
    drives)."""
    line = f"sudo ip link set {channel} up type can bitrate {bitrate or NOMINAL_BITRATE}"
    return f"{line} dbitrate {DATA_BITRATE} fd on" if fd else line


@dataclass(frozen=True)
class BusSpec:
    """A resolved bus: python-can interface name, channel and extra keyword arguments."""

    interface: str
    channel: str | None
    kwargs: dict[str, Any] = field(default_factory=dict)
    source: str = "spec"
    """Where it came from: ``spec``, ``python-can config`` or ``auto``."""

    def __str__(self) -> str:
        if self.interface == "udp_multicast":
            group = self.channel or DEFAULT_GROUP
            group = f"[{group}]" if ":" in group else group
            return f"udp_multicast:{group}:{self.kwargs.get('port', DEFAULT_PORT)}"
        return self.interface if self.channel is None else f"{self.interface}:{self.channel}"


def _parse_udp_channel(rest: str) -> tuple[str, dict[str, Any]]:
    if rest.startswith("["):
        group, _, tail = rest[1:].partition("]")
        port = tail[1:] if tail.startswith(":") else ""
        if tail and not port:
            raise HalConfigError(f"bad udp_multicast channel {rest!r} (use [GROUP]:PORT)")
    elif rest.count(":") == 1:
        group, port = rest.split(":")
    else:
        group, port = rest, ""
    group = group or DEFAULT_GROUP
    try:
        multicast = ipaddress.ip_address(group).is_multicast
    except ValueError:
        multicast = False
    if not multicast:
        raise HalConfigError(f"udp_multicast channel {group!r} is not a multicast IP address")
    kwargs: dict[str, Any] = {}
    if port:
        if not port.isdigit() or not 0 < int(port) < 65536:
            raise HalConfigError(f"bad udp_multicast port {port!r} in {rest!r}")
        kwargs["port"] = int(port)
    return group, kwargs


def parse_spec(spec: str) -> BusSpec:
    """Parse an explicit ``INTERFACE[:CHANNEL]`` spec (not ``auto``)."""
    text = spec.strip()
    interface, _, rest = text.partition(":")
    interface = interface.strip().lower()
    if not interface or interface == AUTO:
        raise HalConfigError(f"bad CAN spec {spec!r}: expected INTERFACE[:CHANNEL]")
    if interface == "udp_multicast":
        group, kwargs = _parse_udp_channel(rest) if rest else (DEFAULT_GROUP, {})
        return BusSpec(interface, group, kwargs)
    if interface not in can.VALID_INTERFACES:
        known = ", ".join(sorted(can.VALID_INTERFACES))
        raise HalConfigError(f"unknown CAN interface {interface!r} in {spec!r} (known: {known})")
    if not rest:
        rest = {"socketcan": DEFAULT_VCAN, "virtual": DEFAULT_VIRTUAL_CHANNEL}.get(interface, "")
    return BusSpec(interface, rest or None)


def _python_can_config() -> dict[str, Any] | None:
    """python-can's configuration when one of its sources names an interface, else ``None``."""
    try:
        sources = [can.rc, can.util.load_environment_config(), can.util.load_file_config()]
        if not any(src.get("interface") or src.get("bustype") for src in sources):
            return None
        return dict(can.util.load_config())
    except (can.CanInterfaceNotImplementedError, ValueError, TypeError, configparser.Error) as exc:
        raise HalConfigError(
            f"python-can configuration (CAN_INTERFACE/CAN_CONFIG or can.conf) is invalid: {exc}"
        ) from exc


def resolve_spec(spec: str | None = None) -> BusSpec:
    """Turn a spec, ``auto`` or ``None`` into a :class:`BusSpec` (no bus is opened)."""
    if spec is not None and spec.strip().lower() != AUTO:
        return parse_spec(spec)
    config = _python_can_config()
    if config is not None:
        interface = str(config.pop("interface"))
        channel = config.pop("channel", None)
        if interface == "udp_multicast" and isinstance(channel, str) and channel:
            group, kwargs = _parse_udp_channel(channel)
            config = {**kwargs, **config}
            channel = group
        elif channel is None:
            channel = parse_spec(interface).channel
        extra = {k: v for k, v in config.items() if v is not None}
        channel = None if channel is None else str(channel)
        return BusSpec(interface, channel, extra, "python-can config")
    if (SYS_CLASS_NET / DEFAULT_VCAN).exists():
        return BusSpec("socketcan", DEFAULT_VCAN, {}, AUTO)
    return BusSpec("udp_multicast", DEFAULT_GROUP, {}, AUTO)


def process_spec(spec: str | None = None) -> BusSpec:
    """:func:`resolve_spec` for a bus between processes (the rig's daemons, a drive check),
    refusing python-can's ``virtual`` bus: it joins the threads of one process only, so a
    daemon on it would wait for peers it can never hear."""
    resolved = resolve_spec(spec)
    if resolved.interface == "virtual":
        origin = "" if resolved.source == "spec" else f" (from {resolved.source})"
        raise HalConfigError(
            f"CAN bus {resolved}{origin}: python-can's virtual bus joins the threads "
            "of one process only, and this command talks to other processes; use "
            "udp_multicast (this host) or socketcan:CHANNEL"
        )
    return resolved


def _transport_error(
    spec: BusSpec, exc: BaseException, bitrate: int | None = None, fd: bool = True
) -> HalTransportError:
    """One line saying what failed and what to do about it (``bitrate``: the bus's, named in
    the line that brings a missing SocketCAN interface up)."""
    err = exc if isinstance(exc, OSError) else exc.__cause__ or exc.__context__
    code = getattr(err, "errno", None)
    name = spec.channel or ""
    if spec.interface == "socketcan":
        if code == errno.EAFNOSUPPORT and name.startswith("vcan"):
            hint = "this kernel has no SocketCAN (AF_CAN); use --can udp_multicast instead"
        elif code == errno.EAFNOSUPPORT:  # a real adapter: udp_multicast never reaches it
            hint = (
                "this kernel has no SocketCAN (AF_CAN): load it with sudo modprobe can_raw "
                "(and the adapter's driver), or open the adapter through its vendor backend "
                "(--can pcan:CHANNEL, kvaser:CHANNEL)"
            )
        elif code == errno.ENODEV or not (SYS_CLASS_NET / name).exists():
            hint = (
                f"create it with: {vcan_hint(name)} (or use --can udp_multicast)"
                if name.startswith("vcan")
                else f"check the adapter, then: {can_up_hint(name, bitrate, fd)}"
            )
        elif code == errno.ENETDOWN and name.startswith("vcan"):
            hint = f"bring it up with: sudo ip link set up {name}"
        elif code == errno.ENETDOWN:  # a CAN adapter needs its bit rates to come up
            hint = f"bring it up with: {can_up_hint(name, bitrate, fd)}"
        else:
            hint = "check the interface with `ip -details link show`, or use --can udp_multicast"
        return HalTransportError(f"cannot open CAN interface socketcan:{name}: {exc}; {hint}")
    if spec.interface == "udp_multicast":
        if isinstance(exc, can.CanInterfaceNotImplementedError):
            hint = "install msgpack: pip install 'python-can[multicast]'"
        else:
            hint = f"check that loopback is up (sudo ip link set lo up), or use {SOCKETCAN_HINT}"
        return HalTransportError(f"cannot open CAN bus {spec}: {exc}; {hint}")
    what = str(exc).rstrip(".")
    if isinstance(exc, NameError) or "library not found" in what:  # no vendor library
        library = VENDOR_LIBRARIES.get(spec.interface, "the adapter's driver and library")
        return HalTransportError(
            f"cannot open CAN bus {spec}: python-can's {spec.interface} interface is missing its "
            f"vendor library ({what}); install {library}"
        )
    return HalTransportError(
        f"cannot open CAN bus {spec}: {what}; check the adapter, its driver and python-can's "
        "interface options"
    )


VENDOR_LIBRARIES = {
    "pcan": "PEAK's driver and PCAN-Basic library (libpcanbasic)",
    "kvaser": "Kvaser's driver and CANlib (linuxcan)",
}
"""What to install for python-can's backends that need a vendor library (named in the error)."""


SOCKETCAN_LOGGER = "can.interfaces.socketcan.socketcan"
"""python-can's SocketCAN logger, which logs its own line when it cannot open a device."""


@contextlib.contextmanager
def _socketcan_logs_held() -> Iterator[None]:
    """Hold what python-can's SocketCAN logger says in this thread while a bus opens: passed on
    if the open succeeds, dropped if it fails (python-can logs "Could not access SocketCAN device
    vcan0" before raising; our one-line error says it and what to do). Other threads' records
    pass untouched."""
    logger = logging.getLogger(SOCKETCAN_LOGGER)
    me = threading.get_ident()
    held: list[logging.LogRecord] = []

    def hold(record: logging.LogRecord) -> bool:
        if record.thread != me:
            return True
        held.append(record)
        return False

    logger.addFilter(hold)
    try:
        yield
    except BaseException:
        held.clear()
        raise
    finally:
        logger.removeFilter(hold)
        for record in held:
            logger.handle(record)


CANFD_MTU = 72


def _check_fd_mtu(name: str) -> None:
    """:class:`HalTransportError` when interface ``name`` cannot carry CAN FD frames (MTU 16)."""
    try:
        mtu = int((SYS_CLASS_NET / name / "mtu").read_text())
    except (OSError, ValueError):
        return  # unknown: let the driver decide
    if mtu < CANFD_MTU:
        raise HalTransportError(
            f"socketcan:{name} has MTU {mtu}: the rig's 16-byte CAN FD frames need "
            f"{CANFD_MTU}; run: sudo ip link set {name} down; sudo ip link set {name} mtu "
            f"{CANFD_MTU}; sudo ip link set up {name}"
        )


def open_bus(
    spec: str | None = None, *, receive_own_messages: bool = False, **kwargs: Any
) -> can.BusABC:
    """Open the bus named by ``spec`` (see the module docstring); extra ``kwargs`` go to it.
    python-can's ``bitrate`` (the cia402 profile passes ``cia402.bitrate``) sets the adapters
    that take one (PCAN, Kvaser, ...); a SocketCAN interface has its own, set by ``ip link``,
    so there it is the rate the hint for a missing interface names. SocketCAN is opened for
    CAN FD (the DSP's frames) unless ``fd=False`` (CANopen's classic frames, which a classic
    adapter of MTU 16 carries).

    Raises :class:`~hal.errors.HalConfigError` for a malformed spec and
    :class:`~hal.errors.HalTransportError` when the transport is unavailable.
    """
    resolved = resolve_spec(spec)
    options = {**resolved.kwargs, **kwargs, "receive_own_messages": receive_own_messages}
    try:
        if resolved.interface == "udp_multicast":
            options.setdefault("hop_limit", 0)
            return LoopbackMulticastBus(channel=resolved.channel or DEFAULT_GROUP, **options)
        socketcan = resolved.interface == "socketcan"
        if socketcan and options.setdefault("fd", True):  # the DSP's 16-byte FD frames (SecOC)
            _check_fd_mtu(resolved.channel or DEFAULT_VCAN)
        with _socketcan_logs_held():
            bus = can.Bus(interface=resolved.interface, channel=resolved.channel, **options)
        if options.get("fd", True) and not socketcan and resolved.interface != "virtual":
            _refuse_classic(bus, resolved)
        return bus
    except HalTransportError:  # already one line saying what to do (e.g. a refused group)
        raise
    except (can.CanError, OSError, ValueError, ImportError, NameError) as exc:
        if isinstance(exc, NameError) and not _raised_in_backend(exc):
            raise  # ours: a bug, not the adapter
        raise _transport_error(
            resolved, exc, options.get("bitrate"), options.get("fd", True)
        ) from exc


def _refuse_classic(bus: can.BusABC, spec: BusSpec) -> None:
    """An adapter python-can opened in classic CAN cannot carry the DSP's 16-byte FD frames:
    shut and refused in one line saying where its FD mode goes (python-can's configuration
    is merged into an explicit spec's arguments too)."""
    if bus.protocol is can.CanProtocol.CAN_20:
        bus.shutdown()
        raise HalTransportError(
            f"CAN bus {spec} opened in classic CAN, but the dsp profile's frames are CAN FD "
            "(16 bytes with SecOC): set fd and the data bit rate in python-can's configuration "
            """(CAN_CONFIG='{"fd": true, "data_bitrate": 2000000}' or ~/can.conf; """
            "docs/tutorials/real-can.md)"
        )


def _raised_in_backend(exc: BaseException) -> bool:
    """Whether ``exc`` was raised inside a python-can interface module: the Kvaser backend
    raises NameError when its vendor library (canlib) is not installed."""
    tb = exc.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    return tb is not None and "can/interfaces/" in tb.tb_frame.f_code.co_filename.replace("\\", "/")


ISOLATED_GROUP_BASE = ipaddress.IPv4Address("239.75.0.0")
"""Isolated udp_multicast specs use groups 239.75.0.1 .. 239.75.255.255 (administratively
scoped, distinct from the default group 239.74.163.2)."""
_ISOLATED_GROUPS = 0xFFFF


class _PortReservation:
    """A UDP port held by this process for its whole life, so no other process is given it.

    The guard sockets are bound to ``127.0.0.1:PORT`` (and ``[::1]:PORT``) *without*
    ``SO_REUSEADDR``/``SO_REUSEPORT``: the kernel then never hands the port out to another
    ``bind(("127.0.0.1", 0))`` (another process's :func:`isolated_spec`) nor to a wildcard bind.
    The buses themselves bind to the group address, which does not overlap the guard's.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._guards: list[socket.socket] = []
        self.port = 0
        self._next = 0
        atexit.register(self.close)

    def close(self) -> None:
        """Give the ports back (at interpreter exit)."""
        with self._lock:
            for guard in self._guards:
                guard.close()
            self._guards = []

    def _reserve(self) -> None:
        guard = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        guard.bind(("127.0.0.1", 0))
        port = guard.getsockname()[1]
        guards = [guard]
        if socket.has_ipv6:
            v6 = socket.socket(socket.AF_INET6, socket.SOCK_DGRAM)
            try:
                v6.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
                v6.bind(("::1", port))
                guards.append(v6)
            except OSError:  # no IPv6 on this host (or ::1 taken: IPv4 specs only anyway)
                v6.close()
        # Earlier ports stay reserved: specs made on them may still be in use.
        self._guards += guards
        self.port, self._next = port, 0

    def next_group(self) -> tuple[str, int]:
        """A (group, port) pair that no bus on this host is bound to and nobody else will get."""
        with self._lock:
            for _ in range(4 * _ISOLATED_GROUPS):
                if not self._guards or self._next >= _ISOLATED_GROUPS:
                    self._reserve()
                self._next += 1
                group = str(ISOLATED_GROUP_BASE + self._next)
                if _unbound(group, self.port):
                    return group, self.port
        raise HalTransportError(  # pragma: no cover - every group on every port taken
            f"no free udp_multicast group/port for an isolated bus; use {SOCKETCAN_HINT}"
        )


def _unbound(group: str, port: int) -> bool:
    """Whether no socket on this host listens on ``group:port`` (or the wildcard ``:port``).

    A bind without reuse options fails with EADDRINUSE if any socket is bound there, whatever
    options it used; so a bus opened on this pair by hand (an explicit port) is detected.
    """
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.bind((group, port))
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                return False
            raise HalTransportError(
                f"cannot bind a UDP socket to {group}:{port}: {exc}; check that lo is up "
                f"(sudo ip link set lo up), or use {SOCKETCAN_HINT}"
            ) from exc
    return True


_RESERVATION = _PortReservation()


def isolated_spec(interface: str) -> str:
    """A spec on ``interface`` that no other test or process uses (for parallel test runs).

    ``virtual`` gets a unique channel name; ``socketcan`` cannot be isolated and returns
    ``socketcan:vcan0``. ``udp_multicast`` gets a group and port pair that cannot be handed out
    twice, without a race: the port is reserved by this process for its lifetime (a guard socket
    the kernel will not let any other process bind over, see :class:`_PortReservation`) and
    each call gets the next group of ``239.75.0.0/16`` on it; a pair some bus is already bound
    to (opened by hand on an explicit port) is skipped. Child processes given the spec share
    the reservation of the process that made it.
    """
    if interface == "virtual":
        return f"virtual:hal-test-{uuid.uuid4().hex[:12]}"
    if interface == "udp_multicast":
        group, port = _RESERVATION.next_group()
        return f"udp_multicast:{group}:{port}"
    if interface == "socketcan":
        return f"socketcan:{DEFAULT_VCAN}"
    raise HalConfigError(f"no isolated spec for interface {interface!r}")


def vcan_available(channel: str = DEFAULT_VCAN) -> bool:
    """Whether a SocketCAN interface named ``channel`` exists on this host and is up."""
    try:
        flags = int((SYS_CLASS_NET / channel / "flags").read_text().strip(), 16)
    except (OSError, ValueError):
        return False
    return bool(flags & 0x1)  # IFF_UP
