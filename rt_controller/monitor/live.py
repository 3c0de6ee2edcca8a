"""Controller side of the live stream: the recorder's ``live`` sink publishing on zenoh.

:class:`LivePublisher` is called by the recorder's writer thread with the MCAP topic and the
already-encoded JSON bytes of each ``/controller/cycle`` and ``/diagnostics`` record, so the tick
pays nothing for it. Its publishers drop rather than block when the link is congested and use a
low priority: a slow or dead monitor never holds up the rig.
"""

from __future__ import annotations

import contextlib

import zenoh

from hal.log_topics import CYCLE_TOPIC, DIAGNOSTICS_TOPIC
from hal.zenoh_session import KEY_CONTROLLER_CYCLE, KEY_CONTROLLER_DIAGNOSTICS, ZenohSession

KEY_OF_TOPIC = {CYCLE_TOPIC: KEY_CONTROLLER_CYCLE, DIAGNOSTICS_TOPIC: KEY_CONTROLLER_DIAGNOSTICS}
"""MCAP topic -> zenoh key of the live stream (the payload is the MCAP message's bytes)."""


class LivePublisher:
    """``publisher(topic, data)`` puts ``data`` on the zenoh key of ``topic``.

    :meth:`close` is idempotent."""

    def __init__(self, session: ZenohSession) -> None:
        self._pubs = {
            topic: session.publisher(key, block=False, priority=zenoh.Priority.DATA_LOW)
            for topic, key in KEY_OF_TOPIC.items()
        }

    def __call__(self, topic: str, data: bytes) -> None:
        pub = self._pubs.get(topic)
        if pub is not None:
            pub.put(data)

    def close(self) -> None:
        pubs, self._pubs = self._pubs, {}
        for pub in pubs.values():
            with contextlib.suppress(Exception):
                pub.undeclare()
