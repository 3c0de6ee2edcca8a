"""The live service in real time and in lockstep (``hil up`` rig, natively over CAN on
``udp_multicast`` and zenoh on loopback, each run on ports of its own) with inputs that come
late:

* a 0.5 s vision dropout (``hil vision --dropout``): stale features put the loop in hold, no NaN
  reaches the bus, the arm stays within limits and the loop converges after the features return;
* a DSP that samples 1 ms after the controller's release: every tick compensates the age of the
  joint state it measured, and the log replays exactly.

Realtime runs check what holds under any host scheduling (the DSP's protection may fire on a
busy host: such a run is reported as not clean); no timing is asserted.
"""

from __future__ import annotations

import re
from typing import Any

import cantools
import numpy as np
import pytest

from hal.can_database import DBC_PATH
from rt_controller.logtools.reader import read_log
from rt_controller.rig.processes import run_rig
from tests.support.live_rig import CFG, PERIOD_S, norm, rig_options

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

TAU_MAX = np.array(CFG.robot.tau_max, dtype=float)
FEATURE_TIMEOUT_S = CFG.controller.feature_timeout_s

DROPOUT = (1.0, 0.5)
"""Vision dropout (start, duration) in seconds of simulation time (the issue: paused 0.5 s)."""
REALTIME_DROPOUT_START_S = 4.0
"""In real time the dropout is on the emulator's clock, which starts before the controller's
first tick; a host loaded far beyond its cores can delay that tick by seconds, so the realtime
run drops out later (the run is long enough to converge again after it)."""
DROPOUT_DURATION_S = 8.0
DQ_LIMIT = 10.0
"""rad/s: the paper scenario never comes near this (observed max 4.2 rad/s on joint 2)."""

DSP_PROTECTION = re.compile(
    r"^(\d+ DSP watchdog trip\(s\)|DSP fault\(s\): .*|\d+ tick\(s\) without an enabled DSP \(.*\))$"
)
"""What may make a realtime run not clean on a busy host: the controller stalled past the DSP's
watchdog (3 periods) or its late commands let the arm exceed a DSP limit; either way the DSP's
protection took the torque off (a fault), and the ticks after ran without an enabled DSP."""


ZERO_TORQUE_MODES = {"no_state", "no_status", "fault", "disarmed", "dsp_restarted"}
"""Cycle ``law`` values in which the controller commands zero torque (a late joint state, or a
DSP that is not enabled; see hal.drive_state)."""


def assert_exit_codes(s: dict[str, Any], *, realtime: bool) -> bool:
    """All processes exit 0; in real time the controller may exit 1 (not clean), but only when
    the DSP's protection fired (see ``DSP_PROTECTION``), never for a lost log record or a crash.
    Whether the run was clean (performance claims hold only for clean runs)."""
    codes = dict(s["exit_codes"])
    clean = codes.get("controller") == 0
    if realtime and codes.get("controller") == 1:
        problems = s["problems"]
        assert problems and all(DSP_PROTECTION.match(p) for p in problems), problems
        print(f"realtime run not clean on this host: {'; '.join(problems)}")
        codes["controller"] = 0
    assert codes == {"controller": 0, "vision": 0, "emulator": 0}, s["exit_codes"]
    return clean


def tx_torques(can_tx: list[dict[str, Any]]) -> np.ndarray:
    """(Tau1, Tau2) of every TorqueCommand frame the controller sent, decoded with the DBC."""
    db = cantools.database.load_file(str(DBC_PATH))
    msg = db.get_message_by_name("TorqueCommand")
    out = [
        (d["Tau1"], d["Tau2"])
        for fr in can_tx
        if fr["arbitration_id"] == msg.frame_id
        for d in [msg.decode(bytes.fromhex(fr["data"]), decode_choices=False)]
    ]
    return np.array(out, dtype=float)


def longest_run(mask: np.ndarray) -> tuple[int, int]:
    """(start index, length) of the longest run of True."""
    best, start = (0, 0), None
    for i, v in enumerate([*mask, False]):
        if v and start is None:
            start = i
        elif not v and start is not None:
            best = max(best, (i - start, start))
            start = None
    length, first = best
    return first, length


@pytest.mark.parametrize("lockstep", [True, False], ids=["lockstep", "realtime"])
def test_vision_dropout_holds_safely_and_recovers(tmp_path, lockstep):
    log = tmp_path / "dropout.mcap"
    start_s, length_s = DROPOUT
    if not lockstep:
        start_s = REALTIME_DROPOUT_START_S
    opts = rig_options(
        log,
        law="rhc",
        lockstep=lockstep,
        duration_s=DROPOUT_DURATION_S,
        extra_vision=["--dropout", f"{start_s}:{length_s}"],
    )
    s = run_rig(opts)
    clean = assert_exit_codes(s, realtime=not lockstep)
    loaded = read_log(log)
    c = loaded.cycles
    t, stale, law = c["sim_time_s"], c["f_stale"], c["law"]

    # the controller flagged the dropout: stale ticks, all of them in hold; the summary's
    # counters are exactly the per-tick records'
    assert s["stale_features"] == int(stale.sum()) > 0
    assert s["stale_states"] == int(c["state_stale"].sum())
    if lockstep:
        assert np.all(law[stale] == "hold")
        assert np.all(law[~stale] == "rhc") and s["stale_states"] == 0
    else:
        # A busy host may make a realtime tick find the joint state late ("no_state"), or the
        # DSP's protection may have taken the torque off ("fault", "no_status", ...): the
        # controller then commands zero torque. Under any scheduling: the law never acts on
        # stale features, and every tick is the law, the hold damper, or zero torque.
        assert not np.any(law[stale] == "rhc")
        zero = ~np.isin(law, ["rhc", "hold"])
        assert set(law[zero]) <= ZERO_TORQUE_MODES, set(law[zero])
        assert np.all(c["tau"][zero] == 0.0)
        assert np.all(law[c["state_stale"].astype(bool)] != "rhc")
    expected = (length_s - FEATURE_TIMEOUT_S) / PERIOD_S  # 20 ticks
    if lockstep:  # deterministic: exactly the window, once the last frame aged past the timeout
        first, n = longest_run(stale)
        assert n == stale.sum() and expected - 1 <= n <= expected + 1, n
        # on images (camera.model = "image", the default) a frame is stamped at the middle of its
        # exposure, camera.exposure_s / 2 before its period's pose: the last frame before the
        # window goes stale up to one tick earlier than an analytic frame stamped at the pose
        lo = start_s + FEATURE_TIMEOUT_S - PERIOD_S
        assert lo - 1e-9 <= t[first] <= start_s + FEATURE_TIMEOUT_S + 0.05
        assert t[first + n - 1] < start_s + length_s
    else:
        # realtime: where and how long the stale stretch is depends on the host's scheduling
        # (the window is on the vision process's clock, and a busy host adds stale stretches of
        # its own, vision frames delayed > 100 ms in transit); what holds under any scheduling
        # is checked: every stale tick is in hold (above), and the longest stale stretch, the
        # dropout's, is held safely (below). Its timing is reported only.
        first, n = longest_run(stale)
        print(
            f"realtime dropout: longest stale stretch {n} ticks from controller t = "
            f"{t[first]:.2f} s ({expected:g} expected); {int(stale.sum())} stale ticks in all, "
            f"{s['stale_states']} without a fresh joint state"
        )
        assert n >= 1
    assert c["f_valid"][stale].all()  # the controller still holds the last valid (old) frame
    assert (c["f_age_ms"][stale] > FEATURE_TIMEOUT_S * 1e3).all()

    # no NaN ever sent: the logged commands and the TorqueCommand frames on the bus
    tau = c["tau"]
    assert np.isfinite(tau).all()
    sent = tx_torques(loaded.can_tx)
    assert len(sent) >= len(tau) and np.isfinite(sent).all()
    # the arm is safe: torque within the amplifier limits, velocities bounded, and in hold the
    # pure damper tau = -2 R dq only takes energy out
    assert (np.abs(tau) <= TAU_MAX + 1e-9).all() and (np.abs(sent) <= TAU_MAX + 0.01).all()
    dq = c["dq"]
    assert np.isfinite(dq).all()
    if lockstep:  # deterministic: the scenario's own bound
        assert np.abs(dq).max() < DQ_LIMIT
    elif clean:  # in real time the bound that holds under any scheduling: the DSP's limits
        assert np.all(np.abs(dq) <= np.array(CFG.dsp.dq_max)), np.abs(dq).max(axis=0)
    else:  # a loop stalled by the host may excite joint 2; the DSP's velocity limit caught it
        dq_max = np.array(CFG.dsp.dq_max)
        if np.any(np.abs(dq) > dq_max):
            assert "velocity_limit" in s["dsp_faults"], s["dsp_faults"]
        print(f"realtime, not clean: max |dq| {np.abs(dq).max(axis=0)} (DSP limit {dq_max})")
    hold = slice(first, first + n)
    acted = c["dq_pred"]  # the velocity the hold acted on: dq brought up to the tick (NaN in
    acted = np.where(np.isfinite(acted), acted, 0.0)  # a tick where the drive was off: tau 0)
    assert np.all(tau[hold] * acted[hold] <= 1e-12), "hold torque must oppose the motion"
    if clean:  # the damper alone acted throughout (no fault let the arm coast)
        assert np.linalg.norm(dq[first + n - 1]) <= np.linalg.norm(dq[first]) + 0.05

    # after the features return the law takes over again and converges (in real time: when the
    # DSP's protection did not have to take the torque off on a busy host)
    after = law[first + n :]
    if lockstep:
        assert np.all(after == "rhc")
    elif clean or not s["dsp_faults"]:  # fresh features again (stale/no_state ticks held above)
        assert np.any(after == "rhc"), "features did not return"
    else:  # a DSP fault is latched: from the first fault tick on, the law never runs again
        faulted = np.flatnonzero(law == "fault")
        assert faulted.size and not np.any(law[faulted[0] :] == "rhc"), sorted(set(law))
    if clean:
        assert s["f_final_norm"] < 1.0, s["f_final"]
        assert norm(c["f"])[-1] < 1.0


def test_a_dsp_sampling_after_the_release_gets_its_states_compensated(tmp_path):
    """Real daemons, real time, a DSP that samples 1 ms after the controller's release
    (``dsp.state_lead_us`` = a period less 1 ms): every tick reads a state about 19 ms old
    (fault injection: without compensation, three runs of three ended in a velocity-limit
    fault). What holds under any scheduling: each tick that ran the law compensated the age it
    measured (``predict_ms`` = ``state_age_ms``, and ``f_predict_ms`` = ``f_age_ms``), the law
    acted on a state other than the measured one, and the log replays exactly."""
    from rt_controller.logtools.replay import replay_log

    rig = tmp_path / "rig.toml"
    rig.write_text("[dsp]\nstate_lead_us = 19000.0\n")
    log = tmp_path / "lag.mcap"
    s = run_rig(rig_options(log, law="ioc", config=str(rig), duration_s=3.0))
    assert_exit_codes(s, realtime=True)
    c = read_log(log, raw=False).cycles
    ran = np.asarray(c["law"]) == "ioc"
    age, predicted = np.asarray(c["state_age_ms"])[ran], np.asarray(c["predict_ms"])[ran]
    assert ran.sum() > 50
    assert np.array_equal(predicted, np.where(age > 0, age, 0.0))
    assert np.median(predicted) > 10.0  # most ticks ran on the previous period's sample
    moved = np.any(np.asarray(c["q_pred"])[ran] != np.asarray(c["q"])[ran], axis=1)
    assert moved[1:][predicted[1:] > 10.0].all()  # (at the first, the arm rests, no torque yet)
    f_age, f_predicted = np.asarray(c["f_age_ms"])[ran], np.asarray(c["f_predict_ms"])[ran]
    assert np.array_equal(f_predicted, np.where(f_age > 0, f_age, 0.0))  # the features too
    result = replay_log(log)
    assert result.ok and result.max_abs_dtau <= 1e-9
