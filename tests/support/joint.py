"""Reading a :class:`~hal.joint_client.JointClient` from a test as the controller does: the
test's own thread reads the bus (:meth:`~hal.joint_client.JointClient.drain` and
:meth:`~hal.joint_client.JointClient.wait_readable`); the client has no thread of its own.

Only one thread may read a client: a test that streams torque from a thread reads the bus in
that thread, and the test's main thread then only looks at ``client.status`` and the like."""

from __future__ import annotations

import math
import time
from collections.abc import Callable

from hal.can_codec import DspStatus, JointState
from hal.errors import HalTimeoutError
from hal.joint_client import JointClient


def read_until(client: JointClient, pred: Callable[[], object], timeout_s: float) -> bool:
    """Read the bus until ``pred()`` is true (True) or ``timeout_s`` passed (False)."""
    deadline = time.monotonic() + timeout_s
    while True:
        client.drain()
        if pred():
            return True
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return False
        client.wait_readable(min(remaining, 0.01))


def read_for(client: JointClient, seconds: float) -> None:
    """Keep reading the bus for ``seconds`` (instead of sleeping with a client open)."""
    read_until(client, lambda: False, seconds)


def next_state(client: JointClient, timeout_s: float) -> JointState:
    """The first joint state completed after this call; :class:`HalTimeoutError` if none
    comes within ``timeout_s``."""
    seen = client.states_received
    if not read_until(client, lambda: client.states_received > seen, timeout_s):
        raise HalTimeoutError(f"no joint state within {timeout_s:g} s on {client.bus.channel_info}")
    return client.latest_state(max_age_s=math.inf)


def next_status(client: JointClient, timeout_s: float) -> DspStatus:
    """The first DspStatus received after this call (what the DSP says now, not a backlog);
    :class:`HalTimeoutError` if none comes within ``timeout_s``."""
    client.drain()  # what waited on the bus is older than this call
    seen = client.stats.statuses
    if not read_until(client, lambda: client.stats.statuses > seen, timeout_s):
        raise HalTimeoutError(f"no DspStatus within {timeout_s:g} s on {client.bus.channel_info}")
    status = client.status
    assert status is not None
    return status
