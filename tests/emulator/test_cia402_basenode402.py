"""Issue 39's target for the emulated drives: "An independent master made only of canopen's own
BaseNode402, with none of our code, brings each emulated drive to OPERATION ENABLED in CST. It
reads 0x6061 = 10, and a torque step gives 0x6064 and 0x606C traces that match the arm model."

The master below uses canopen only (BaseNode402, its Network's SYNC producer and NMT, periodic
RPDOs), reading the drives' description from the shipped EDS; the arm model it is compared
with is plant_emulator's ArmPhysics integrated directly, step by step, with the torques the
drives report in 0x6077.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest
from canopen.profiles.p402 import BaseNode402

from hal.cia402_od import EDS_PATH
from hal.config import RigConfig, plant_view
from plant_emulator.arm import ArmPhysics
from tests.support.cia402 import REPLY_TIMEOUT_S, drives_on_virtual_bus

pytestmark = pytest.mark.slow

STEP_PERMILLE = (200, 100)
"""The torque step: 2 Nm of joint 1's 10 Nm rated torque, 0.1 Nm of joint 2's 1 Nm (the light
direct-drive arm turns 1 rad in 0.6 s with it)."""
WIDE_LIMITS = {"dsp.q_min": (-50.0, -50.0), "dsp.q_max": (50.0, 50.0), "dsp.dq_max": (83.0, 83.0)}
"""The emulator's joint limits out of the way: the trace, not the limit faults, is under test."""
SAMPLES_AFTER_STEP = 25
"""SYNC periods recorded with the step applied on both joints (0.5 s at 50 Hz)."""


class Trace:
    """(statusword, position, velocity, torque) per SYNC of one drive, from its two TPDOs."""

    def __init__(self, node: BaseNode402, enough: threading.Event) -> None:
        self.position: list[int] = []
        self.velocity: list[int] = []
        self.torque: list[int] = []
        self.recording = False
        self._enough = enough
        node.tpdo[1].add_callback(self._tpdo1)
        node.tpdo[2].add_callback(self._tpdo2)

    def _tpdo1(self, pdo) -> None:
        if self.recording:
            self.position.append(pdo["Position actual value"].raw)

    def _tpdo2(self, pdo) -> None:
        if self.recording:
            self.velocity.append(pdo["Velocity actual value"].raw)
            self.torque.append(pdo["Torque actual value"].raw)
            if sum(1 for t in self.torque if t) >= SAMPLES_AFTER_STEP:
                self._enough.set()


def _patient(node: BaseNode402) -> None:
    """BaseNode402's own timeouts, widened for a shared, loaded test host."""
    node.TIMEOUT_SWITCH_STATE_FINAL = 10 * REPLY_TIMEOUT_S
    node.TIMEOUT_SWITCH_STATE_SINGLE = REPLY_TIMEOUT_S
    node.TIMEOUT_CHECK_TPDO = REPLY_TIMEOUT_S
    node.TIMEOUT_SWITCH_OP_MODE = REPLY_TIMEOUT_S
    node.sdo.RESPONSE_TIMEOUT = REPLY_TIMEOUT_S


def test_basenode402_enables_both_drives_in_cst_and_a_torque_step_matches_the_arm_model():
    cfg = RigConfig().with_overrides(WIDE_LIMITS)
    period = 1.0 / cfg.rates.control_hz
    with drives_on_virtual_bus(cfg) as bench:
        network = bench.master
        nodes = []
        for node_id in (cfg.cia402.node_id_1, cfg.cia402.node_id_2):
            node = BaseNode402(node_id, str(EDS_PATH))
            network.add_node(node)
            _patient(node)
            node.nmt.send_command(0x82)  # reset communication
            node.nmt.wait_for_bootup(REPLY_TIMEOUT_S)
            node.setup_402_state_machine()  # reads the PDO maps by SDO
            node.op_mode = "CYCLIC SYNCHRONOUS TORQUE"
            assert node.sdo[0x6061].raw == 10
            assert node.op_mode == "CYCLIC SYNCHRONOUS TORQUE"
            node.rpdo[1]["Target torque"].raw = 0
            nodes.append(node)
        enough = [threading.Event() for _ in nodes]
        traces = [Trace(node, e) for node, e in zip(nodes, enough, strict=True)]
        rated = [node.sdo[0x6076].raw for node in nodes]  # mNm
        ipr = [node.sdo[0x608F][1].raw / node.sdo[0x608F][2].raw / (2 * np.pi) for node in nodes]

        network.sync.start(period)
        try:
            network.nmt.send_command(0x01)  # start every node at the same SYNC
            for trace in traces:
                trace.recording = True
            for node in nodes:
                node.rpdo[1].start(period)  # synchronous RPDO, sent every period
                node.state = "OPERATION ENABLED"
                assert node.state == "OPERATION ENABLED"
                assert node.op_mode == "CYCLIC SYNCHRONOUS TORQUE"
            for node, step in zip(nodes, STEP_PERMILLE, strict=True):
                node.rpdo[1]["Target torque"].raw = step
            for event in enough:
                assert event.wait(30 * REPLY_TIMEOUT_S), "the torque step never showed in 0x6077"
        finally:
            network.sync.stop()
            for node in nodes:
                node.rpdo[1].stop()
        for trace in traces:
            trace.recording = False

    n = min(min(len(t.position), len(t.torque)) for t in traces)
    firsts = [int(np.argmax(np.array(t.torque) != 0)) for t in traces]
    n = min(n, max(firsts) + SAMPLES_AFTER_STEP)  # the SYNCs after the test's wait are not used
    for trace, step, first in zip(traces, STEP_PERMILLE, firsts, strict=True):
        # 0x6077 is a step: zero until one SYNC, the commanded value from then on
        torque = np.array(trace.torque[:n])
        assert (torque[:first] == 0).all() and (torque[first:] == step).all()

    arm = ArmPhysics(plant_view(cfg).robot)
    q = np.array(cfg.scenario.q0, dtype=float)
    dq = np.array(cfg.scenario.dq0, dtype=float)
    position = np.array([t.position[:n] for t in traces]).T
    velocity = np.array([t.velocity[:n] for t in traces]).T
    torque = np.array([t.torque[:n] for t in traces]).T
    model_position, model_velocity = [], []
    for k in range(n):  # TPDO k: the state at SYNC k; 0x6077 k: the torque over [k, k+1]
        model_position.append(np.round(q * ipr))
        model_velocity.append(np.round(dq * ipr))
        tau = torque[k] * np.array(rated) / 1e6
        q, dq = arm.integrate(q, dq, tau, 1.0 / cfg.rates.physics_hz, cfg.rates.substeps)
    np.testing.assert_allclose(position, np.array(model_position), atol=1, rtol=0)
    np.testing.assert_allclose(velocity, np.array(model_velocity), atol=1, rtol=0)
    moved = np.abs(position[-1] - position[0])
    assert (moved > 10_000).all(), f"the step hardly moved the arm: {moved} increments"
