"""Remote tuning authenticated, or refused (rt_controller/monitor/access.py): a real foxglove-sdk
server over TLS (a self-signed certificate made here with the openssl CLI, 127.0.0.1 only) and
independent WebSocket clients (``websockets``, tests/support/foxglove_ws.py); the link to the
controller played in-process by the real ParameterServer (tests of test_monitor_tuning.py)."""

from __future__ import annotations

import json
import os
import shutil
import ssl
import subprocess
from pathlib import Path

import pytest
from websockets.exceptions import ConnectionClosed, InvalidHandshake

from hal.config import RigConfig
from hal.secoc import derive, load_key_file, write_key_file
from hal.zenoh_session import free_loopback_port
from rt_controller.cli import main
from rt_controller.errors import ControllerConfigError
from rt_controller.monitor.access import AccessGate, TlsIdentity, exposure, tuning_token
from rt_controller.monitor.bridge import MonitorBridge
from rt_controller.monitor.tuning import TuningFrontEnd
from tests.support.foxglove_ws import FoxgloveClient
from tests.support.param_link import KEY, TICK, LoopbackLink

TOKEN = tuning_token(KEY)
OPERATOR = {"/hil/arm", "/hil/disarm", "/hil/mark", "/hil/switch_law", "/hil/reset_scenario"}


@pytest.fixture(scope="module")
def certificate(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A self-signed certificate for 127.0.0.1 and its key (mode 0600)."""
    if shutil.which("openssl") is None:
        pytest.skip("the openssl CLI is not installed")
    d = tmp_path_factory.mktemp("tls")
    cert, key = d / "cert.pem", d / "key.pem"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
         "-nodes", "-days", "2", "-keyout", str(key), "-out", str(cert), "-subj", "/CN=127.0.0.1",
         "-addext", "subjectAltName=IP:127.0.0.1"],
        check=True, capture_output=True,
    )  # fmt: skip
    key.chmod(0o600)
    return cert, key


@pytest.fixture
def serve_tls(certificate):
    """``start(allow_tuning)`` -> (link, wss url, ssl context trusting the certificate)."""
    bridges: list[MonitorBridge] = []
    cert, key = certificate

    def start(allow_tuning: bool = True):
        link = LoopbackLink()
        gate = AccessGate("token", KEY)
        tuning = TuningFrontEnd(link, KEY, allow_tuning=allow_tuning, gate=gate)
        port = free_loopback_port()
        tls = TlsIdentity.load(cert, key)
        bridge = MonitorBridge(RigConfig(), link, port=port, tuning=tuning, tls=tls)
        bridges.append(bridge)
        assert bridge.url == f"wss://127.0.0.1:{port}"
        ctx = ssl.create_default_context(cafile=str(cert))
        # TLS 1.2: about one TLS 1.3 connection in a hundred got no answer to its WebSocket
        # handshake for 10 s, and websockets' client then hung for good in its reader's SSL
        # read (readable by the 1.3 session tickets, no data behind them) when it gave up
        ctx.maximum_version = ssl.TLSVersion.TLSv1_2
        return link, bridge.url, ctx

    yield start
    for b in bridges:
        b.close()


def test_over_tls_the_client_with_the_token_sets_kp_and_one_without_cannot(serve_tls):
    link, url, ctx = serve_tls()
    stranger = FoxgloveClient.open(url, ssl=ctx)
    operator = FoxgloveClient.open(url, ssl=ctx)
    stranger.subscribe_parameters(["hil.token", "hil.last_outcome", "gains.kp"])
    # reads work for everyone
    assert stranger.get_parameters(["gains.kp"]) == {"gains.kp": 0.13}
    # a set without the token is refused, with the reason, and never reaches the controller
    out = stranger.set_parameters({"gains.kp": 0.3, "hil.at_tick": TICK})
    assert out["gains.kp"] == 0.13 and "hil.token" in out["hil.last_outcome"]
    assert link.service.param_set == 0 and link.service.cfg.gains.kp == 0.13
    # a wrong token admits nothing
    out = stranger.set_parameters({"hil.token": "0" * 64, "gains.kp": 0.3})
    assert "wrong access token" in out["hil.last_outcome"] and out["gains.kp"] == 0.13
    assert out["hil.token"] == ""  # the token is never echoed
    # the operator presents the token, then tunes
    out = operator.set_parameters({"hil.token": TOKEN})
    assert "accepted" in out["hil.last_outcome"] and out["hil.token"] == ""
    out = operator.set_parameters({"gains.kp": 0.3, "hil.at_tick": TICK})
    assert out["gains.kp"] == 0.3 and "accepted at tick 10" in out["hil.last_outcome"]
    assert link.service.cfg.gains.kp == 0.3 and link.service.param_set == 1
    # the stranger still cannot, though the operator's connection was admitted
    out = stranger.set_parameters({"gains.kp": 0.5})
    assert out["gains.kp"] == 0.3 and "hil.token" in out["hil.last_outcome"]
    assert link.service.cfg.gains.kp == 0.3
    # services: refused without the token (the controller never asked), answered with it
    stranger.wait_services(OPERATOR)
    for name in ("/hil/disarm", "/hil/arm", "/hil/mark"):
        refused = stranger.call_service(name, {"note": "x"})
        assert refused["accepted"] is False and "hil.token" in refused["reason"]
    law = stranger.call_service("/hil/switch_law", {"law": "rhc"})
    assert not law["accepted"] and link.service.cfg.controller.law == "ioc"
    operator.wait_services(OPERATOR)
    assert operator.call_service("/hil/switch_law", {"law": "rhc"})["accepted"]
    assert link.service.cfg.controller.law == "rhc"
    assert operator.call_service("/hil/disarm", {})["accepted"]
    # the SDK publishes each set's reply to the subscribers: the token's is there, blanked
    sent = json.dumps(stranger.parameter_updates)
    assert "access token accepted" in sent and TOKEN not in sent
    # a new connection starts without the operator's admission
    again = FoxgloveClient.open(url, ssl=ctx)
    assert "hil.token" in again.set_parameters({"gains.kp": 0.7})["hil.last_outcome"]
    assert link.service.cfg.gains.kp == 0.3
    for c in (stranger, operator, again):
        c.close()


def test_the_tls_server_refuses_a_plain_websocket(serve_tls):
    """Refused by a server that is there: the handshake fails (``InvalidHandshake``, stable
    since websockets 10; or the server closes the connection), not the connect. A connect that
    fails (nobody listens) is the helper's AssertionError, which does not satisfy the check."""
    _link, url, ctx = serve_tls()
    with pytest.raises((InvalidHandshake, ConnectionClosed)):
        FoxgloveClient.open(url.replace("wss://", "ws://"), attempts=1, open_timeout=5)
    FoxgloveClient.open(url, ssl=ctx).close()  # and it was there, serving TLS


def test_a_remote_read_only_view_takes_no_change_and_no_token():
    link = LoopbackLink()
    gate = AccessGate("closed")
    tuning = TuningFrontEnd(link, KEY, allow_tuning=False, gate=gate)
    port = free_loopback_port()  # "closed" is the mode of a plain remote view; served here
    with MonitorBridge(RigConfig(), link, port=port, tuning=tuning):
        client = FoxgloveClient.open(f"ws://127.0.0.1:{port}")
        assert client.get_parameters(["gains.kp"]) == {"gains.kp": 0.13}
        out = client.set_parameters({"hil.token": TOKEN, "gains.kp": 0.3})
        assert out["gains.kp"] == 0.13 and "read-only" in out["hil.last_outcome"]
        assert link.service.param_set == 0 and gate.counts["admitted"] == 0
        client.get_parameters([])  # the server has advertised its services by now
        assert client.services == {}  # not even the mark
        client.close()


def test_exposure_rule():
    assert exposure("127.0.0.1", allow_remote=False, allow_tuning=True, tls=False) == "open"
    assert exposure("::1", allow_remote=False, allow_tuning=True, tls=True) == "token"
    assert exposure("192.0.2.1", allow_remote=True, allow_tuning=False, tls=False) == "closed"
    assert exposure("192.0.2.1", allow_remote=True, allow_tuning=True, tls=True) == "token"
    with pytest.raises(ControllerConfigError, match="TLS"):
        exposure("192.0.2.1", allow_remote=True, allow_tuning=True, tls=False)
    with pytest.raises(ControllerConfigError, match="--allow-remote"):
        exposure("192.0.2.1", allow_remote=False, allow_tuning=False, tls=True)


def _key_file(tmp_path: Path) -> Path:
    return write_key_file(tmp_path / "rig.key")


def test_remote_tuning_without_tls_is_refused_in_one_line(tmp_path: Path, capsys):
    # 192.0.2.1 (TEST-NET-1) is no address of this host: nothing could be served on it anyway
    key = _key_file(tmp_path)
    argv = ["monitor", "--host", "192.0.2.1", "--allow-remote", "--allow-tuning"]
    assert main([*argv, "--key-file", str(key), "--duration", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "TLS" in err and "--allow-tuning" in err


def test_tls_options_come_as_a_pair_and_are_checked(tmp_path: Path, certificate, capsys):
    cert, key = certificate
    assert main(["monitor", "--tls-cert", str(cert), "--duration", "1"]) == 2
    assert "--tls-key" in capsys.readouterr().err
    bad = tmp_path / "open.pem"
    bad.write_bytes(key.read_bytes())
    bad.chmod(0o644)
    assert main(["monitor", "--tls-cert", str(cert), "--tls-key", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "chmod 600" in err
    assert main(["monitor", "--tls-cert", str(key), "--tls-key", str(key)]) == 2
    assert "no PEM certificate" in capsys.readouterr().err


def test_print_token_is_the_rig_keys_derived_key(tmp_path: Path, capsys):
    key_file = _key_file(tmp_path)
    assert main(["monitor", "--print-token", "--key-file", str(key_file)]) == 0
    printed = capsys.readouterr().out.strip()
    key = load_key_file(key_file)
    assert printed == derive(key, "foxglove-tuning").hex() == tuning_token(key)
    other = write_key_file(tmp_path / "other.key")
    assert tuning_token(load_key_file(other)) != printed
    os.remove(other)
