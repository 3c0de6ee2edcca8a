"""The rig's zenoh endpoint rule, without zenoh: ``transport.zenoh_endpoint`` is an IPv4
loopback ``tcp/127.x.x.x:PORT`` (nothing leaves the host; ``--zenoh-config`` is the way to
several hosts). The configuration checks it when it loads and :mod:`hal.zenoh_session` when
a session opens, with this one parser."""

from __future__ import annotations

import ipaddress
import re

from hal.errors import HalConfigError

_LOOPBACK_RE = re.compile(r"^tcp/(127\.\d{1,3}\.\d{1,3}\.\d{1,3}):(\d{1,5})$")


def _is_ipv4(host: str) -> bool:
    try:
        return ipaddress.IPv4Address(host).is_loopback
    except ValueError:
        return False


def parse_loopback_endpoint(endpoint: str) -> tuple[str, int]:
    """``(host, port)`` of a ``tcp/127.x.x.x:PORT`` endpoint, else :class:`HalConfigError`."""
    m = _LOOPBACK_RE.match(endpoint)
    if m is None or not 0 < int(m.group(2)) < 65536 or not _is_ipv4(m.group(1)):
        raise HalConfigError(
            f"transport.zenoh_endpoint: {endpoint!r} is not an IPv4 loopback endpoint "
            "tcp/127.0.0.1:PORT; use --zenoh-config FILE for multi-host setups"
        )
    return m.group(1), int(m.group(2))
