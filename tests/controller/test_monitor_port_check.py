"""``hil up --monitor``'s port check before the rig starts: a port a server listens on is
refused; one whose last connection only lingers in TIME_WAIT (a Foxglove client that just
disconnected) is free, as it is for the monitor's own server."""

from __future__ import annotations

import socket

import pytest

import rt_controller.rig.processes
from rt_controller.cli import main


class Started(Exception):
    """The port check passed and the rig would have started."""


@pytest.fixture
def no_rig(monkeypatch: pytest.MonkeyPatch) -> None:
    def started(*_: object, **__: object) -> None:
        raise Started

    monkeypatch.setattr(rt_controller.rig.processes, "run_rig", started)


def listener() -> socket.socket:
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    return srv


def up(port: int) -> list[str]:
    return ["up", "--lockstep", "--duration", "1", "--monitor-port", str(port)]


def test_a_port_in_time_wait_is_free(no_rig: None) -> None:
    srv = listener()
    port = srv.getsockname()[1]
    client = socket.create_connection(("127.0.0.1", port))
    conn, _ = srv.accept()
    conn.close()  # the server side closes first: its end of the connection is in TIME_WAIT
    client.close()
    srv.close()
    with pytest.raises(Started):
        main(up(port))


def test_a_port_a_server_listens_on_is_refused(no_rig: None, capsys) -> None:
    srv = listener()
    try:
        assert main(up(srv.getsockname()[1])) == 2
    finally:
        srv.close()
    assert "--monitor: cannot listen on 127.0.0.1:" in capsys.readouterr().err
