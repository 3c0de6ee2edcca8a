"""``ZenohSession.has_subscriber``: the one "is anyone listening / wait until someone is" of the
rig's publishers (camera poses, frames, sim control, a log's replay): it waits interruptibly and
answers False, never zenoh's ZError, once the publisher or its session is closed."""

from __future__ import annotations

import threading

from hal.zenoh_session import open_session

KEY = "hil/test/subscriber"


def test_no_subscriber_then_one(endpoint):
    with (
        open_session(listen=True, endpoint=endpoint) as hub,
        open_session(listen=False, endpoint=endpoint) as client,
    ):
        pub = hub.publisher(KEY)
        assert hub.has_subscriber(pub) is False
        assert hub.has_subscriber(pub, timeout_s=0.05) is False
        sub = client.subscribe(KEY, lambda _payload: None)
        assert hub.has_subscriber(pub, timeout_s=10.0) is True
        sub.undeclare()
        pub.undeclare()


def test_a_set_stop_ends_the_wait_at_once(endpoint):
    stop = threading.Event()
    stop.set()
    with open_session(listen=True, endpoint=endpoint) as hub:
        pub = hub.publisher(KEY)
        assert hub.has_subscriber(pub, timeout_s=3600.0, stop=stop) is False
        pub.undeclare()


def test_a_closed_publisher_or_session_has_no_subscriber(endpoint):
    with (
        open_session(listen=True, endpoint=endpoint) as hub,
        open_session(listen=False, endpoint=endpoint) as client,
    ):
        client.subscribe(KEY, lambda _payload: None)
        pub, gone = hub.publisher(KEY), hub.publisher(KEY)
        assert hub.has_subscriber(pub, timeout_s=10.0)
        gone.undeclare()
        assert hub.has_subscriber(gone) is False
        hub.close()
        assert hub.has_subscriber(pub, timeout_s=0.05) is False
