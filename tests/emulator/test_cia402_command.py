"""``hil emulator`` with ``hardware.profile = "cia402"`` as a process on a host-local udp_multicast
bus (and on SocketCAN vcan0 with ``-m vcan``): both drives boot, follow a canopen master's SYNC,
and when the SYNC stops every drive is in FAULT with an EMCY 0x8700 on the bus; SIGTERM then
ends the emulator cleanly with its counters."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time

import canopen
import pytest
from canopen.sdo import SdoCommunicationError

from hal.bus import isolated_spec, open_bus
from hal.cia402_od import EDS_PATH, EMCY_SYNC
from tests.support import REPO, hil_command, run_hil
from tests.support.vcan import requires_vcan

pytestmark = pytest.mark.integration

SYNC_LOSS_PERIODS = 50.0
"""One second of SYNC silence at 50 Hz faults the drives: the test's own pauses never do."""
START_TIMEOUT_S = 60.0
"""A cold start imports numpy, numba, canopen and loads the kernels: generous on a shared host."""


def answers(node: canopen.RemoteNode, timeout_s: float) -> bool:
    """Whether the drive answers an SDO read within ``timeout_s`` (the process has started)."""
    node.sdo.RESPONSE_TIMEOUT = 0.5
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            node.sdo[0x1000].read()
        except SdoCommunicationError:
            continue
        node.sdo.RESPONSE_TIMEOUT = 5.0
        return True
    return False


def wait_for(predicate, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


@pytest.mark.parametrize(
    "transport",
    ["udp_multicast", pytest.param("socketcan", marks=[pytest.mark.vcan, requires_vcan])],
)
def test_the_emulator_command_serves_two_drives_that_fault_when_sync_stops(tmp_path, transport):
    config = tmp_path / "rig.toml"
    config.write_text(  # the profile from the config, as hil up hands it to the emulator
        f'[hardware]\nprofile = "cia402"\n[cia402]\nsync_loss_periods = {SYNC_LOSS_PERIODS}\n'
    )
    spec = isolated_spec(transport)
    with open_bus(spec) as bus:
        network = canopen.Network(bus)
        network.connect()  # listening before the drives boot
        nodes = [canopen.RemoteNode(i, str(EDS_PATH)) for i in (1, 2)]
        for node in nodes:
            network.add_node(node)
        args = ["emulator", "--can", spec, "--config", str(config)]
        proc = subprocess.Popen(
            [*hil_command(), *args, "--no-vision-link", "--json"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
            cwd=REPO,
        )
        try:
            for node in nodes:
                assert answers(node, START_TIMEOUT_S), f"node {node.id} never answered"
                node.tpdo.read()
                node.sdo[0x6060].raw = 10
            network.nmt.send_command(0x01)  # start all
            for _ in range(3):
                for node in nodes:
                    node.tpdo[1].is_received = False
                network.sync.transmit()
                for node in nodes:
                    assert wait_for(lambda n=node: n.tpdo[1].is_received, 5.0)
            for node in nodes:
                assert node.tpdo[1]["Statusword"].raw & 0x4F == 0x40
            # the SYNC stops here: the drives' own monitor must fault them
            for node in nodes:
                codes = lambda n=node: [e.code for e in n.emcy.log]  # noqa: E731
                assert wait_for(lambda c=codes: EMCY_SYNC in c(), START_TIMEOUT_S)
                assert node.sdo[0x6041].raw & 0x4F == 0x08  # FAULT
                assert node.sdo[0x6077].raw == 0
            os.killpg(proc.pid, signal.SIGTERM)
            out, err = proc.communicate(timeout=START_TIMEOUT_S)
        finally:
            if proc.poll() is None:  # pragma: no cover - only on a hang
                os.killpg(proc.pid, signal.SIGKILL)
                print("DEBUG", proc.communicate())
            network.notifier.stop()
    assert proc.returncode == 0, err
    assert "serving CiA 402 drives (nodes 1, 2)" in err
    assert "fault: node 1 EMCY 0x8700 (SYNC loss)" in err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["syncs"] == 3
    assert summary["callback_errors"] is None  # --no-vision-link: no zenoh session
    assert summary["sim_time_s"] == 0.0  # no drive was enabled: the world's clock held
    assert [d["state"] for d in summary["drives"]] == ["FAULT", "FAULT"]
    assert [d["emcys"] for d in summary["drives"]] == [["0x8700"], ["0x8700"]]


def test_duration_counts_wall_seconds_in_realtime_when_no_master_syncs(tmp_path):
    """In realtime ``--duration`` is wall time (as the DSP profile's): with no master sending
    SYNC the world's clock holds, and the emulator must still end when its seconds are up."""
    config = tmp_path / "rig.toml"
    config.write_text('[hardware]\nprofile = "cia402"\n')
    args = ["emulator", "--can", isolated_spec("udp_multicast"), "--config", str(config)]
    # on a hang (the emulator never ends) run_hil kills it and raises TimeoutExpired
    done = run_hil([*args, "--no-vision-link", "--duration", "1", "--json"], START_TIMEOUT_S)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    assert summary["syncs"] == 0 and summary["sim_time_s"] == 0.0
