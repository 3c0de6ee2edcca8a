"""Rogue senders against the real daemons (emulator, vision, controller as processes; host-local
udp_multicast CAN; zenoh on loopback): issue 12's attacks, each rejected, counted by reason and
reported, never applied.

The attacker is another process on the host without the rig's key (``hil up`` makes a fresh key
per run): it forges frames with a valid CRC and rolling counter but its own key, or replays
authentic frames it captured off the bus. The rigs run in lockstep (deterministic physics, so
"converged as if alone" is a sharp check on a loaded host). Every test prints one line of the
attack table (``ATTACK ...``; ``pytest -s`` shows them). No wall-clock verdicts: the tests wait
with generous bounds and check invariants of the log and the counters.
"""

from __future__ import annotations

import base64
import json
import math
import secrets
import time
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from hal.bus import isolated_spec, open_bus
from hal.can_codec import DspCodec
from hal.can_database import load_database
from hal.config import load_config
from hal.drive_state import DspCommand
from hal.joint_client import JointClient
from hal.vision_codec import FeatureMsg, decode_features, encode_features
from hal.zenoh_session import KEY_FEATURES, open_session
from rt_controller.logtools.reader import read_log
from rt_controller.rig.options import RigOptions
from rt_controller.rig.processes import Child, Rig
from tests.support import free_endpoint

pytestmark = pytest.mark.integration

WAIT_S = 120.0
LAWS = ("pbc", "ioc", "rhc")
F_CONVERGED_PX = 1.0
"""A lockstep ioc run of the paper scenario ends within a fraction of a px of the target."""


def _cycles(log: Path) -> int:
    try:
        return read_log(log, raw=False).n_cycles
    except Exception:
        return 0


def _child(rig: Rig, name: str) -> Child:
    return next(c for c in rig.children if c.name == name)


def _wait_cycles(log: Path, n: int, rig: Rig) -> None:
    deadline = time.monotonic() + WAIT_S
    while _cycles(log) < n:
        ctl = _child(rig, "controller")
        if ctl.proc.poll() is not None:
            pytest.fail(f"controller exited early ({ctl.proc.returncode}):\n{ctl.tail()}")
        if time.monotonic() > deadline:
            pytest.fail(f"fewer than {n} cycles logged")
        time.sleep(0.05)


def _opts(tmp_path: Path, **kw: Any) -> tuple[RigOptions, Path]:
    log = tmp_path / "run.mcap"
    base: dict[str, Any] = {
        "law": "ioc",
        "duration_s": 120.0,  # simulated: lockstep runs some 10-40x faster than real time
        "lockstep": True,  # deterministic: the verdicts do not depend on this host's load
        "can": isolated_spec("udp_multicast"),
        "zenoh_endpoint": free_endpoint(),
        "log": log,
        "extra_emulator": ["--json"],
    }
    base.update(kw)
    return RigOptions(**base), log


def _finish(rig: Rig) -> tuple[int, dict[str, Any], str, dict[str, Any]]:
    """Wait for the controller; stop the rest: (status, summary, stderr, emulator counters)."""
    ctl = _child(rig, "controller")
    try:
        ctl.proc.wait(WAIT_S)
    except Exception:
        pytest.fail(f"controller still running:\n{ctl.tail()}")
    lines = [ln for ln in ctl.output().splitlines() if ln.startswith("{")]
    assert lines, ctl.tail()
    rig.stop()
    emu = _child(rig, "emulator")
    emu_lines = [ln for ln in emu.output().splitlines() if ln.startswith("{")]
    assert emu_lines, emu.tail()
    return ctl.proc.returncode, json.loads(lines[-1]), ctl.tail(), json.loads(emu_lines[-1])


def _assert_normal_run(summary: dict[str, Any], log: Path) -> None:
    """The run went on as if the attacker were not there: armed throughout, no DSP fault,
    converged."""
    assert summary["dsp_faults"] == {}, summary["dsp_faults"]
    assert summary["watchdog_trips"] == 0
    assert not summary["drive_ticks"], summary["drive_ticks"]  # never disarmed
    assert summary["f_final_norm"] < F_CONVERGED_PX, summary["f_final_norm"]
    laws = set(np.asarray(read_log(log, raw=False).column("law")))
    assert laws & set(LAWS) and not laws & {"disarmed", "fault", "dsp_restarted"}, laws


def _table(attack: str, counted: str, outcome: str) -> None:
    print(f"ATTACK | {attack} | {counted} | {outcome}")


def _rogue_key() -> bytes:
    return secrets.token_bytes(32)


def test_forged_torque_is_never_applied(tmp_path):
    """A rogue node with a valid CRC and counter but no rig key commands full torque at 1 kHz
    for a second (issue: q2 went to the encoder limit)."""
    opts, log = _opts(tmp_path)
    sent = 0
    with Rig(opts) as rig:
        rig.start()
        _wait_cycles(log, 50, rig)
        with JointClient.open(opts.can, key=_rogue_key()) as rogue:
            rogue.enable()  # FAULT_RESET + ENABLE, forged too
            t_end = time.monotonic() + 1.0
            while time.monotonic() < t_end:
                rogue.send_torque(150.0, 15.0)
                sent += 1
                time.sleep(0.001)
        rc, summary, err, emu = _finish(rig)
    rejected = emu["rejected"]
    assert rejected["bad_mac"] >= sent + 4, rejected  # + FAULT_RESET, ENABLE (x2), DISABLE
    assert rejected["accepted"] > 0 and rejected["counter_jump"] == 0, rejected
    _assert_normal_run(summary, log)
    q = np.asarray(read_log(log, raw=False).column("q"), dtype=float)
    assert np.all(np.abs(q) < math.pi), np.abs(q).max()  # never driven to a limit
    assert rc == 1 and "DSP rejected" in err.strip().splitlines()[-1], err
    _table(
        "forged TorqueCommand 150/15 N·m at 1 kHz, 1 s",
        f"DSP bad_mac {rejected['bad_mac']} (sent {sent} + commands)",
        f"never applied; |f| {summary['f_final_norm']:.2f} px, J {summary['J']:.1f}; run exit 1",
    )


def test_forged_disable_and_enable_are_ignored(tmp_path):
    opts, log = _opts(tmp_path)
    sent = 0
    with Rig(opts) as rig:
        rig.start()
        _wait_cycles(log, 50, rig)
        with JointClient.open(opts.can, key=_rogue_key()) as rogue:
            for _ in range(20):
                rogue.send_command(DspCommand.DISABLE, repeat=3)
                time.sleep(0.05)
                rogue.send_command(DspCommand.ENABLE, repeat=3)
                time.sleep(0.05)
                sent += 6
        rc, summary, err, emu = _finish(rig)
    rejected = emu["rejected"]
    assert rejected["bad_mac"] >= sent, rejected
    _assert_normal_run(summary, log)
    laws = list(read_log(log, raw=False).column("law"))
    assert "disarmed" not in laws
    assert rc == 1, err
    _table(
        "forged DspControl DISABLE / ENABLE (20 x 3 each)",
        f"DSP bad_mac {rejected['bad_mac']} (sent {sent})",
        f"never disarmed; |f| {summary['f_final_norm']:.2f} px; run exit 1",
    )


def test_forged_joint_state_is_never_used(tmp_path):
    opts, log = _opts(tmp_path)
    forged_q = (1.2345, -2.3456)
    sent = 0
    with Rig(opts) as rig:
        rig.start()
        _wait_cycles(log, 50, rig)
        rogue = DspCodec(key=_rogue_key())
        with open_bus(opts.can) as bus:
            t_end = time.monotonic() + 1.0
            sample = 0
            while time.monotonic() < t_end:
                for msg in rogue.encode_state(forged_q, (0.0, 0.0), sample):
                    bus.send(msg)
                    sent += 1
                sample += 1
                time.sleep(0.001)
        rc, summary, err, _ = _finish(rig)
    can_rx = summary["rejections"]["can_rx"]
    assert can_rx["bad_mac"] >= sent, can_rx
    q = np.asarray(read_log(log, raw=False).column("q"), dtype=float)
    assert not np.any(np.all(np.abs(q - np.array(forged_q)) < 1e-3, axis=1))  # never used
    _assert_normal_run(summary, log)
    assert rc == 1 and "failed authentication" in err.strip().splitlines()[-1], err
    _table(
        "forged JointPosition/JointVelocity at 1 kHz, 1 s",
        f"controller can_rx bad_mac {can_rx['bad_mac']} (sent {sent})",
        f"never used; |f| {summary['f_final_norm']:.2f} px; run exit 1",
    )


def test_replayed_authentic_frames_are_stale(tmp_path):
    """Frames captured off the bus (authentic: the rig's own MAC) and sent again later: the
    DSP's FAULT_RESET/ENABLE/torque and the DSP's state and status, all with old freshness."""
    opts, log = _opts(tmp_path)
    db = load_database()
    ctl_ids = {s.frame_id for s in db.sent_by("Controller")}
    dsp_ids = {s.frame_id for s in db.sent_by("DSP")}
    captured: list[can.Message] = []
    with open_bus(opts.can) as sniffer, Rig(opts) as rig:
        rig.start()
        deadline = time.monotonic() + WAIT_S
        next_check = 0.0
        while True:
            msg = sniffer.recv(timeout=0.05)
            if msg is not None and msg.arbitration_id in ctl_ids | dsp_ids:
                captured.append(msg)
            now = time.monotonic()
            if now >= next_check:  # reading the log is slow: not after every frame
                next_check = now + 0.2
                if _cycles(log) >= 200 and len(captured) >= 500:
                    break
            assert now < deadline, f"only {len(captured)} frames captured"
        # replay everything captured (incl. the controller's FAULT_RESET + ENABLE at start)
        replay_ctl = [m for m in captured if m.arbitration_id in ctl_ids]
        replay_dsp = [m for m in captured if m.arbitration_id in dsp_ids][-2000:]
        for msg in replay_ctl + replay_dsp:
            sniffer.send(msg)
            time.sleep(0.0002)
        rc, summary, err, emu = _finish(rig)
    rejected, can_rx = emu["rejected"], summary["rejections"]["can_rx"]
    assert rejected["stale_freshness"] >= len(replay_ctl), rejected
    assert rejected["bad_mac"] == 0, rejected  # authentic frames: only freshness stops them
    assert can_rx["stale_freshness"] >= len(replay_dsp), can_rx
    assert can_rx["bad_mac"] == 0, can_rx
    _assert_normal_run(summary, log)
    assert rc == 1, err
    _table(
        f"replayed authentic frames ({len(replay_ctl)} controller, {len(replay_dsp)} DSP)",
        f"DSP stale_freshness {rejected['stale_freshness']}, controller stale_freshness "
        f"{can_rx['stale_freshness']}",
        f"never applied or used; |f| {summary['f_final_norm']:.2f} px; run exit 1",
    )


def test_rogue_feature_publisher_is_rejected(tmp_path):
    """Well-formed, fresh features from a rogue zenoh publisher at 200 Hz (issue: used on 100
    of 110 ticks); both with its own source id and with the real vision source's id."""
    opts, log = _opts(tmp_path)
    forged_f = (33.0, -44.0)
    sent = 0
    with Rig(opts) as rig:
        rig.start()
        _wait_cycles(log, 50, rig)
        real = [decode_features(base64.b64decode(r["data"])) for r in read_log(log).vision]
        source, frame = real[-1].source, max(m.frame for m in real)
        key = _rogue_key()
        with open_session(load_config(), listen=False, endpoint=opts.zenoh_endpoint) as session:
            pub = session.publisher(KEY_FEATURES)
            t_end = time.monotonic() + 1.0
            while time.monotonic() < t_end:
                sent += 1
                src = source if sent % 2 else 777
                msg = FeatureMsg(frame + 100 + sent, time.monotonic_ns(), 0, 0, forged_f,
                                 True, False, src)  # fmt: skip
                pub.put(encode_features(msg, key))
                time.sleep(0.005)
            pub.undeclare()
        rc, summary, err, _ = _finish(rig)
    features = summary["rejections"]["features"]
    assert features["bad_mac"] == sent, features
    f = np.asarray(read_log(log, raw=False).column("f"), dtype=float)
    assert not np.any(np.all(f == np.array(forged_f), axis=1))  # never used
    _assert_normal_run(summary, log)
    assert rc == 1 and "vision message(s) failed authentication" in err, err
    _table(
        "rogue zenoh publisher, fresh features at 200 Hz, 1 s",
        f"controller features bad_mac {features['bad_mac']} (sent {sent})",
        f"never used; |f| {summary['f_final_norm']:.2f} px; run exit 1",
    )
