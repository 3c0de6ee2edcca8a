"""``hil monitor`` on a port another server listens on says so at once (exit 2), before it
waits for the zenoh hub: it once waited for the hub and, with no rig up yet, blamed the hub
("no hub ... after N s"), hiding the port until the rig was started."""

from __future__ import annotations

import socket

from hal.zenoh_session import free_loopback_port
from rt_controller.cli import main


def test_a_taken_port_is_refused_before_the_hub_wait(capsys) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as srv:
        srv.bind(("127.0.0.1", 0))
        srv.listen(1)
        port = srv.getsockname()[1]
        endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"  # no hub there
        argv = ["monitor", "--port", str(port), "--zenoh-endpoint", endpoint, "--duration", "2"]
        assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"127.0.0.1:{port}" in err and "--port" in err, err
    assert "no hub" not in err and "waiting for the zenoh hub" not in err, err
