"""Ctrl-C while ``hil param`` waits for an answer: a set for a later tick is answered when that
tick comes (up to 600 s by default), and zenoh's wait takes no signal. The controller here is a
real :class:`~rt_controller.calibration.link.ParameterServer` on a loopback zenoh hub whose loop
never reaches the tick."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading

import pytest

from hal.config import RigConfig
from hal.secoc import write_key_file
from hal.zenoh_session import free_loopback_port, open_session
from rt_controller.calibration.link import ParameterServer
from rt_controller.calibration.parameters import ParameterService
from tests.support.proc import WAIT_S


class Waiting(ParameterService):
    """A controller that queues a set and never reaches its tick; :attr:`arrived` is set when
    one came."""

    def __init__(self) -> None:
        super().__init__(RigConfig())
        self.arrived = threading.Event()

    def submit(self, request) -> None:
        super().submit(request)
        self.arrived.set()


@pytest.mark.parametrize(("sig", "status"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_ctrl_c_while_a_set_waits_for_its_tick_ends_hil_param_at_once(tmp_path, sig, status):
    from hal.secoc import load_key_file

    key_file = write_key_file(tmp_path / "rig.key")
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    hub = open_session(listen=True, endpoint=endpoint)
    service = Waiting()
    queryable = ParameterServer(service, load_key_file(key_file)).attach(hub)
    cmd = [sys.executable, "-m", "rt_controller.cli", "param", "set", "gains.kp=0.2"]
    cmd += ["--at-tick", "100", "--timeout", "60", "--key-file", str(key_file)]
    proc = subprocess.Popen(
        [*cmd, "--zenoh-endpoint", endpoint],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert service.arrived.wait(WAIT_S), "the set never reached the controller"
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=WAIT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        queryable.undeclare()
        hub.close()
    assert proc.returncode == status and out == ""
    (line,) = err.strip().splitlines()  # no stack dump, no "no answer within 60 s"
    name = signal.Signals(sig).name
    assert line == (
        f"hil param: interrupted by {name} before the answer; the set was sent and may still "
        "take effect (the run's log says)"
    )
