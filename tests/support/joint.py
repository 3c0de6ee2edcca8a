"""Reading a :class:`~hal.joint_client.JointClient` from a test as the controller does: the
test's own thread reads the bus (:meth:`~hal.joint_client.JointClient.drain` and
:meth:`~hal.joint_client.JointClient.wait_readable`); the client has no thread of its own.

Only one thread may read a client: a test that streams torque from a thread reads the bus in
that thread, and the test's main thread then only looks at ``client.status`` and the like."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable

from hal.can_frames import DspStatus, JointState
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


class TripRearm:
    """When a client that keeps the DSP armed must re-arm it: once per watchdog trip.

    Feed it every DspStatus in order (:meth:`~hal.joint_client.JointClient.take_statuses`, not
    only the newest: a batch read may end on a later status). After a re-arm the DSP may go on
    saying tripped for a while (seconds under user-mode Linux, until it handles the re-arm);
    those statuses are the same trip. A tripped status is a new trip when a status without the
    trip came since the last re-arm (the DSP left the fault, so it handled the re-arm: nothing
    else resets a fault) or when it counts more trips than the one re-armed. The trip count
    alone does not do: ``DspStatus.WatchdogTrips`` is 4 bits and stays at 15, so a client that
    compared counts never re-armed a 16th trip and the DSP stayed off under a live client."""

    def __init__(self) -> None:
        self._pending = False
        """A re-arm went out that no status without the trip has answered yet."""
        self._rearmed_at = 0
        """``WatchdogTrips`` of the trip the last re-arm was for."""

    def new_trip(self, statuses: Iterable[DspStatus]) -> bool:
        """Whether ``statuses`` (every one since the last call, oldest first) show a trip not
        re-armed yet; True means the caller re-arms now (``enable()``)."""
        trips = None
        for st in statuses:
            if not st.watchdog_tripped:
                self._pending = False
            elif not self._pending or st.watchdog_trips > self._rearmed_at:
                trips = st.watchdog_trips
        if trips is None:
            return False
        self._pending, self._rearmed_at = True, trips
        return True
