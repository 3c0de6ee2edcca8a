"""Zenoh session factory: loopback-only configuration, open/close, errors, pub/sub round trip."""

from __future__ import annotations

import json
import threading
import time

import pytest
import zenoh

from hal.config import RigConfig, load_config
from hal.errors import HalConfigError, HalStopped, HalTransportError
from hal.resources import open_resources
from hal.vision_codec import FeatureMsg, encode_features
from hal.vision_receivers import FeatureDecoder
from hal.zenoh_session import (
    KEY_CAMERA_POSE,
    KEY_FEATURES,
    loopback_config_dict,
    open_session,
    parse_loopback_endpoint,
)
from tests.support import wait_until


def _endpoints(doc: dict) -> list[str]:
    return [*doc["listen"]["endpoints"], *doc["connect"]["endpoints"]]


def test_key_expressions_are_the_contract():
    assert KEY_FEATURES == "hil/vision/features"
    assert KEY_CAMERA_POSE == "hil/emulator/camera_pose"
    assert RigConfig().transport.zenoh_endpoint == "tcp/127.0.0.1:7447"


@pytest.mark.parametrize("listen", [True, False])
def test_default_config_is_loopback_only(listen):
    doc = loopback_config_dict("tcp/127.0.0.1:7447", listen=listen)
    assert doc["scouting"]["multicast"]["enabled"] is False
    assert doc["scouting"]["gossip"]["enabled"] is False
    assert _endpoints(doc) == ["tcp/127.0.0.1:7447"]
    assert doc["mode"] == ("router" if listen else "client")
    # zenoh itself reads it that way (no default [::] listener sneaks in)
    z = zenoh.Config.from_json5(json.dumps(doc))
    assert json.loads(z.get_json("scouting/multicast/enabled")) is False
    assert json.loads(z.get_json("scouting/gossip/enabled")) is False
    assert json.loads(z.get_json("listen/endpoints")) == doc["listen"]["endpoints"]
    assert json.loads(z.get_json("connect/endpoints")) == doc["connect"]["endpoints"]


@pytest.mark.parametrize(
    "bad",
    [
        "tcp/0.0.0.0:7447",
        "tcp/192.168.1.10:7447",
        "tcp/[::1]:7447",
        "tcp/localhost:7447",
        "udp/127.0.0.1:7447",
        "tcp/127.0.0.1:0",
        "tcp/127.0.0.1:99999",
        "tcp/127.0.0.999:7447",
        " tcp/127.0.0.1:7447",
        "127.0.0.1:7447",
    ],
)
def test_non_loopback_endpoints_are_refused(bad):
    with pytest.raises(HalConfigError, match="--zenoh-config"):
        parse_loopback_endpoint(bad)
    with pytest.raises(HalConfigError):
        open_session(endpoint=bad)


def test_open_close_is_idempotent_and_tracked(endpoint):
    with open_session(load_config(), listen=True, endpoint=endpoint) as s:
        assert s.listening and s.mode == "router" and not s.closed
        assert s.config["scouting"]["multicast"]["enabled"] is False
        assert _endpoints(s.config) == [endpoint]
        assert any(endpoint in label for label in open_resources())
        s.close()
        s.close()
        assert s.closed
    assert open_resources() == []


def test_client_session_is_loopback_only(endpoint):
    with (
        open_session(listen=True, endpoint=endpoint) as hub,
        open_session(listen=False, endpoint=endpoint) as client,
    ):
        assert hub.listening and not client.listening
        assert client.mode == "client"
        assert client.config["listen"]["endpoints"] == []
        assert client.config["connect"]["endpoints"] == [endpoint]
        assert client.config["scouting"]["multicast"]["enabled"] is False
        assert client.config["scouting"]["gossip"]["enabled"] is False


def test_port_in_use_is_one_clear_line(endpoint):
    with open_session(listen=True, endpoint=endpoint):
        with pytest.raises(HalTransportError, match="port in use") as info:
            open_session(listen=True, endpoint=endpoint)
        assert "\n" not in str(info.value) and ".rs:" not in str(info.value)


def test_auto_role_takes_the_hub_if_free_else_connects(endpoint):
    with (
        open_session(endpoint=endpoint, listen=None) as first,
        open_session(endpoint=endpoint, listen=None) as second,
    ):
        assert first.listening and not second.listening


def test_default_role_is_client_so_no_start_order_fights_over_the_port(endpoint):
    with open_session(listen=True, endpoint=endpoint), open_session(endpoint=endpoint) as s:
        assert not s.listening and s.mode == "client"
    with pytest.raises(HalTransportError, match="no hub"):
        open_session(endpoint=endpoint, wait_s=0.2)


def test_client_without_hub_gives_up_clearly(endpoint):
    with pytest.raises(HalTransportError, match="no hub at"):
        open_session(listen=False, endpoint=endpoint, wait_s=0.3)


def test_client_wait_is_interrupted_by_stop_event(endpoint):
    """Waiting for a hub that never comes ends on the stop request, not on ``wait_s`` (an hour
    here: a wait that ignored the stop would hit pytest's timeout instead)."""
    stop = threading.Event()
    timer = threading.Timer(0.2, stop.set)
    timer.start()
    try:
        with pytest.raises(HalStopped, match="stopped while waiting for the hub"):
            open_session(listen=False, endpoint=endpoint, wait_s=3600.0, stop_event=stop)
    finally:
        timer.join()
    assert stop.is_set()


def test_client_started_before_hub_connects_when_it_appears(endpoint):
    out: dict = {}

    def connect() -> None:
        try:
            out["s"] = open_session(listen=False, endpoint=endpoint, wait_s=20.0)
        except Exception as exc:  # pragma: no cover - reported below
            out["err"] = exc

    th = threading.Thread(target=connect)
    th.start()
    time.sleep(0.3)
    with open_session(listen=True, endpoint=endpoint):
        th.join()
        assert "err" not in out, out.get("err")
        out["s"].close()


def test_config_file_replaces_defaults(tmp_path, endpoint):
    path = tmp_path / "zenoh.json5"
    scouting = "scouting: { multicast: { enabled: false }, gossip: { enabled: false } }"
    path.write_text(
        f"// user's own zenoh config\n{{ mode: 'router', listen: {{ endpoints: ['{endpoint}'] }},"
        f" {scouting} }}"
    )
    cfg = load_config().with_overrides({"transport.zenoh_config": str(path)})
    with open_session(cfg) as s:
        assert s.source == str(path) and s.mode == "router" and s.config is None


def test_bad_config_file_is_a_config_error(tmp_path):
    with pytest.raises(HalConfigError, match="no such file"):
        open_session(config_file=str(tmp_path / "missing.json5"))
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: 'peer', bogus: 1 }")
    with pytest.raises(HalConfigError, match="bogus"):
        open_session(config_file=str(bad))


def test_pub_sub_round_trip_between_two_sessions(endpoint):
    with (
        open_session(listen=True, endpoint=endpoint) as hub,
        open_session(listen=False, endpoint=endpoint) as client,
    ):
        decoder = FeatureDecoder(max_age_ns=None)
        client.subscribe(KEY_FEATURES, decoder.feed)
        pub = hub.publisher(KEY_FEATURES)
        assert wait_until(lambda: pub.matching_status.matching)
        sent = [FeatureMsg(k, time.monotonic_ns(), 0, k, (float(k), -1.0)) for k in range(20)]
        for msg in sent:
            pub.put(encode_features(msg))
        assert wait_until(lambda: decoder.counts.received == len(sent))
        assert decoder.latest == sent[-1]
        assert decoder.counts.accepted == len(sent) and decoder.counts.rejected == 0


def test_client_to_client_goes_through_the_hub(endpoint):
    with (
        open_session(listen=True, endpoint=endpoint),
        open_session(listen=False, endpoint=endpoint) as a,
        open_session(listen=False, endpoint=endpoint) as b,
    ):
        got: list[bytes] = []
        b.subscribe("hil/test/x", got.append)
        pub = a.publisher("hil/test/x", block=True)
        assert wait_until(lambda: pub.matching_status.matching)
        pub.put(b"hello")
        assert wait_until(lambda: got == [b"hello"])


def test_callback_exceptions_are_counted_not_raised(endpoint):
    with open_session(listen=True, endpoint=endpoint) as s:

        def boom(_payload: bytes) -> None:
            raise RuntimeError("bug in a callback")

        s.subscribe("hil/test/boom", boom)
        pub = s.publisher("hil/test/boom")
        pub.put(b"x")
        assert wait_until(lambda: s.callback_errors == 1)
