"""``hil replay``: offline replay reproduces a recorded run, detects a changed gain, writes
``--out`` logs, survives truncation; ``--republish`` plays the raw inputs onto CAN and zenoh.

Logs are built without the live daemons: the in-process plant (:class:`World`, as ``hil
simulate`` uses it) is driven by :meth:`Controller.decide`, and each tick is recorded with
:class:`CycleRecorder` in the daemon's record shape, together with the raw inputs the daemon
would have received (DSP frames, vision payloads).
"""

from __future__ import annotations

import base64
import json
import math
import time
from pathlib import Path

import can
import numpy as np
import pytest

from hal.bus import isolated_spec, open_bus
from hal.can_codec import ControllerCodec, DspCodec
from hal.can_database import load_database
from hal.config import RigConfig
from hal.secoc import SecOCVerifier, rig_key
from hal.vision_codec import FeatureMsg, decode_features, encode_features
from hal.zenoh_session import KEY_FEATURES, free_loopback_port, open_session
from plant_emulator.world import World
from rt_controller.cli import main
from rt_controller.control.controller import Controller
from rt_controller.errors import LogError
from rt_controller.logtools.reader import read_log
from rt_controller.logtools.replay import TIMING_FIELDS, abs_diff, replay_log
from rt_controller.logtools.republish import republish_log
from rt_controller.runtime.cycle_record import Timing, cycle_record, decision_fields, vec2
from rt_controller.runtime.recorder import CycleRecorder
from tests.support import wait_until

TICKS = 120
NO_FEATURES_YET = (0,)
"""Ticks before any features arrived: f is NaN (null in the log) and the loop holds."""
STALE = range(40, 52)
"""Ticks with stale features: the last f is held and so is the arm; the law restarts after."""
NO_STATE = (70,)
"""Ticks without joint state: q is NaN, zero torque."""
T0_NS = 1_000_000_000_000
"""Monotonic time of tick 0 in the synthetic log: deliberately unrelated to this machine's clock
(a fresh machine's ``CLOCK_MONOTONIC`` may read less, a long-running one more)."""
STAMP_AGE_NS = 4_000_000
VISION_RX_LEAD_NS = 10_000
"""The synthetic vision message is received this long before the tick's wake-up."""


def daemon_record(
    ctl: Controller, k: int, wake: int, t_s: float, q, dq, f, d, stale, late=(0, 0.0, 0.0)
) -> dict:
    """The cycle record the daemon's tick writes, with fixed synthetic timings; ``late`` is the
    tick's (lateness in ns, state and feature ages it compensated in ms)."""
    f_stale, state_stale = stale
    lateness_ns, predict_ms, f_predict_ms = late
    f_ok = bool(np.all(np.isfinite(f)))
    return cycle_record(
        tick=k,
        t_ns=wake,
        sim_time_s=t_s,
        timing=Timing(
            lateness_us=lateness_ns / 1e3,
            read_us=3.0,
            solve_us=40.0,
            write_us=5.0,
            cycle_us=50.0,
            e2e_us=math.nan if state_stale else 60.0,
        ),
        q=q,
        dq=dq,
        f=f,
        f_age_ms=4.0 if f_ok else math.nan,
        state_age_ms=math.nan if state_stale else max(0.5, predict_ms),
        f_valid=f_ok,
        f_stale=f_stale,
        state_stale=state_stale,
        decision=decision_fields(ctl, d),
        predict_ms=predict_ms,
        f_predict_ms=f_predict_ms,
    )


def record_run(path: Path, cfg: RigConfig, ticks: int = TICKS, *, lockstep: bool = True) -> Path:
    """A daemon-shaped log of a closed-loop run on the in-process plant (no transports)."""
    world, ctl = World(cfg), Controller(cfg)
    sc = cfg.scenario
    ctl.warm_up()  # the daemon's warm-up
    dsp, own = DspCodec(), ControllerCodec()
    period = cfg.rates.control_period_ns
    last_f = np.full(2, np.nan)
    info = {"clock": "lockstep" if lockstep else "realtime", "can": "virtual"}
    prev: tuple[np.ndarray, np.ndarray] = (np.array(sc.q0), np.array(sc.dq0))
    with CycleRecorder(path, cfg, run_info=info, chunk_size=4096) as rec:
        for k in range(ticks):
            wake, t_s = T0_NS + k * period, k * period / 1e9
            q, dq, f = world.measure()
            state_stale = k in NO_STATE
            f_stale = k in NO_FEATURES_YET or k in STALE
            # raw inputs as the DSP and the vision process would have sent them
            rec.record_can(dsp.encode_sync(k), wake - 30_000, "rx")
            if not state_stale:
                for msg in dsp.encode_state(vec2(q), vec2(dq), k):
                    rec.record_can(msg, wake - 20_000, "rx")
            if not f_stale:
                feat = FeatureMsg(k, wake - STAMP_AGE_NS, k * period, k, vec2(f), True, lockstep)
                rec.record_vision(encode_features(feat), wake - VISION_RX_LEAD_NS)
                last_f = f
            if state_stale:
                q, dq = np.full(2, np.nan), np.zeros(2)
            f = last_f if f_stale else f
            # realtime: some ticks run late, and every third one on the previous period's state
            late = (0, 0.0, 0.0)
            if not lockstep and not state_stale and k > 0:
                f_age = 0.0 if f_stale else 7.5 + 3.25 * (k % 4)
                late = (700_123 * (k % 5 == 0), 19.25 if k % 3 == 0 else 2.5, f_age)
                if k % 3 == 0:
                    q, dq = prev
            prev = (q, dq)
            d = ctl.decide(
                t_s,
                q,
                dq,
                f,
                f_stale=f_stale,
                state_stale=state_stale,
                state_age_s=late[1] / 1e3,
                feature_age_s=late[2] / 1e3,
                now_s=t_s + late[0] / 1e3 / 1e6,  # as the daemon does
            )
            stale = (f_stale, state_stale)
            rec.record_cycle(daemon_record(ctl, k, wake, t_s, q, dq, f, d, stale, late))
            torque = own.encode_torque(float(d.tau[0]), float(d.tau[1]), tick=k)
            rec.record_can(torque, wake + 50_000, "tx")
            if k == 2:
                rec.record_can(torque, wake + 60_000, "rx")  # a bus echoing our own frame
            world.hold(d.tau, cfg.rates.substeps)
    return path


@pytest.fixture(scope="module", params=["ioc", "rhc"])
def recorded(request, tmp_path_factory) -> Path:
    cfg = RigConfig().with_overrides({"controller.law": request.param})
    return record_run(tmp_path_factory.mktemp(request.param) / "run.mcap", cfg)


@pytest.fixture(scope="module")
def ioc_log(tmp_path_factory) -> Path:
    return record_run(tmp_path_factory.mktemp("ioc-small") / "run.mcap", RigConfig())


# ------------------------------------------------------------------------------- offline replay


def test_the_recorded_run_covers_hold_no_state_and_nan(recorded):
    log = read_log(recorded)
    laws = list(log.cycles["law"])
    assert log.n_cycles == TICKS and not log.truncated
    assert {laws[k] for k in (*NO_FEATURES_YET, *STALE)} == {"hold"}
    assert laws[NO_STATE[0]] == "no_state" and np.all(log.cycles["tau"][NO_STATE[0]] == 0)
    assert np.all(np.isnan(log.cycles["q"][NO_STATE[0]]))
    assert np.all(np.isnan(log.cycles["f"][0])) and np.isnan(log.cycles["cost"][0])
    assert laws[-1] == read_log(recorded).config.controller.law


def test_replay_reproduces_u_and_tau(recorded):
    result = replay_log(recorded)
    assert result.ok and result.ticks == TICKS and not result.truncated
    assert result.max_abs_du <= 1e-9 and result.max_abs_dtau <= 1e-9
    assert result.ticks_over_tol == 0 and result.law_mismatches == 0
    assert np.all(result.tau[NO_STATE[0]] == 0.0)
    assert result.notes == []


def test_a_realtime_log_with_predicted_states_replays_exactly(tmp_path):
    """Realtime ticks that ran late and on a state they compensated (``predict_ms``, the
    torque history on the ``sim_time_s + lateness`` axis) replay to the last bit; the
    prediction mattered (without it the same ticks decide otherwise)."""
    cfg = RigConfig().with_overrides({"controller.law": "rhc"})
    path = record_run(tmp_path / "rt.mcap", cfg, lockstep=False)
    log = read_log(path)
    assert np.count_nonzero(np.asarray(log.cycles["predict_ms"]) > 15.0) > 30
    assert np.count_nonzero(np.asarray(log.cycles["f_predict_ms"]) > 10.0) > 30
    result = replay_log(path)
    assert result.ok and result.max_abs_du <= 1e-9 and result.max_abs_dtau <= 1e-9
    blind = Controller(cfg)
    blind.warm_up()
    c = log.cycles
    taus = [
        blind.decide(
            float(c["sim_time_s"][i]),
            np.asarray(c["q"][i]),
            np.asarray(c["dq"][i]),
            np.asarray(c["f"][i]),
            f_stale=bool(c["f_stale"][i]),
            state_stale=bool(c["state_stale"][i]),
        ).tau
        for i in range(log.n_cycles)
    ]
    assert abs_diff(np.asarray(taus), np.asarray(c["tau"])).max() > 1e-3


def test_cli_json_within_tolerance(recorded, capsys):
    assert main(["replay", str(recorded), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    for key in ("ticks", "max_abs_du", "max_abs_dtau", "worst_tick", "ticks_over_tol", "tol"):
        assert key in out
    assert out["ok"] is True and out["truncated"] is False
    assert out["ticks"] == TICKS and out["tol"] == 1e-9 and out["ticks_over_tol"] == 0


def test_changed_gain_fails_with_a_clear_message(recorded, capsys):
    assert main(["replay", str(recorded), "--set", "gains.kp=0.2"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert err[0].startswith("hil replay: replay differs from the log: max |dtau| = ")
    assert " at tick " in err[0] and "(tol 1e-09)" in err[0]

    cfg = read_log(recorded).config.with_overrides({"gains.kp": 0.2})
    result = replay_log(recorded, cfg_override=cfg)
    assert not result.ok and result.max_abs_dtau > 1e-6 and result.ticks_over_tol > 0
    assert result.worst_tick is not None and result.law_mismatches == 0
    assert result.tau[NO_STATE[0]].tolist() == [0.0, 0.0]  # no_state still compares equal


def test_cli_text_output_and_json_failure(ioc_log, capsys):
    assert main(["replay", str(ioc_log)]) == 0
    assert "max_abs_dtau" in capsys.readouterr().out
    assert main(["replay", str(ioc_log), "--set", "gains.kp=0.2", "--json"]) == 1
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    assert out["ok"] is False and out["ticks_over_tol"] > 0
    assert "replay differs from the log" in captured.err


def test_out_writes_a_readable_replayed_log(ioc_log, tmp_path):
    out = tmp_path / "replayed.mcap"
    result = replay_log(ioc_log, out=out)
    assert result.ok and result.out == out
    src, new = read_log(ioc_log), read_log(out)
    assert not new.truncated and new.n_cycles == TICKS and new.config == src.config
    assert new.run_info["replay_of"] == str(ioc_log)
    assert new.run_info["source.clock"] == "lockstep" and new.run_info["clock"] == "lockstep"
    np.testing.assert_array_equal(new.cycles["tau"], result.tau)
    np.testing.assert_array_equal(new.cycles["u"], src.cycles["u"])
    np.testing.assert_array_equal(new.cycles["t_ns"], src.cycles["t_ns"])
    np.testing.assert_array_equal(new.cycles["q"], src.cycles["q"])  # NaN rows included
    assert list(new.cycles["law"]) == list(src.cycles["law"])
    for name in TIMING_FIELDS:
        if name in src.cycles:
            assert np.all(new.cycles[name] == 0.0), name
    assert len(new.can_rx) == len(src.can_rx) and len(new.vision) == len(src.vision)
    assert [r["data"] for r in new.can_rx] == [r["data"] for r in src.can_rx]
    assert replay_log(out).ok  # the replayed log replays too


def test_truncated_log_replays_as_far_as_it_goes(ioc_log, tmp_path, capsys):
    data = ioc_log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    result = replay_log(cut, allow_partial=True)
    assert result.truncated and 0 < result.ticks < TICKS and result.ok and result.matches
    assert any("truncated" in note for note in result.notes)
    assert main(["replay", str(cut), "--json", "--allow-partial"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["truncated"] is True and out["ticks"] == result.ticks and out["ok"] is True


@pytest.mark.parametrize("damage", ["cut", "bit_flips"])
def test_a_damaged_log_fails_the_replay_unless_partial_is_allowed(
    ioc_log, tmp_path, capsys, damage
):
    """Half a log, or bit flips in the middle of it: the ticks before the damage match, but the
    replay is not a success (rc 1, one line naming the damage) without --allow-partial."""
    data = bytearray(ioc_log.read_bytes())
    if damage == "cut":
        data = data[: len(data) // 2]
    else:  # every 512th byte of the middle third: some land in a chunk's records, whose
        # CRC then fails (flips that land only in a message index go unseen by any reader)
        for i in range(len(data) // 3, 2 * len(data) // 3, 512):
            data[i] ^= 0xFF
    bad = tmp_path / f"{damage}.mcap"
    bad.write_bytes(bytes(data))
    result = replay_log(bad)
    assert result.truncated and result.ticks < TICKS and result.matches and not result.ok
    assert main(["replay", str(bad), "--json"]) == 1
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    assert out["ok"] is False and out["matches"] is True and out["truncated"] is True
    line = captured.err.strip()
    assert "\n" not in line and line.startswith("hil replay: log is incomplete or damaged")
    assert "--allow-partial" in line


def test_missing_cycle_records_are_noted(ioc_log, tmp_path, cfg):
    """A gap in the ticks (recorder drops) is reported, not hidden."""
    log = read_log(ioc_log, raw=False)
    path = tmp_path / "gap.mcap"
    with CycleRecorder(path, cfg) as rec:
        for i in [*range(10), *range(15, 30)]:
            rec.record_cycle(
                {
                    k: v[i].tolist() if hasattr(v[i], "tolist") else v[i]
                    for k, v in log.cycles.items()
                }
            )
    result = replay_log(path)
    assert result.ticks == 25 and result.ok  # ioc has no memory: still equal
    assert any("5 cycle record(s) missing" in note for note in result.notes)


@pytest.mark.parametrize(
    "content", [None, b"not an mcap file at all", "empty"], ids=["missing", "garbage", "empty"]
)
def test_bad_file_is_exit_2(tmp_path, cfg, capsys, content):
    path = tmp_path / "bad.mcap"
    if content == "empty":
        CycleRecorder(path, cfg).close()
    elif content is not None:
        path.write_bytes(content)
    with pytest.raises(LogError):
        replay_log(path)
    assert main(["replay", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hil replay: error:")


@pytest.mark.parametrize("bad", ["gains.kp", "nosuch.key=1", 'gains.kp="x"'])
def test_bad_set_is_exit_2(ioc_log, capsys, bad):
    assert main(["replay", str(ioc_log), "--set", bad]) == 2
    assert "error:" in capsys.readouterr().err


def test_config_file_overrides_the_log(ioc_log, tmp_path):
    toml = tmp_path / "rig.toml"
    toml.write_text("[gains]\nkp = 0.2\n")
    assert main(["replay", str(ioc_log), "--config", str(toml)]) == 1
    toml.write_text("[gains]\nkp = 0.13\n")
    assert main(["replay", str(ioc_log), "--config", str(toml)]) == 0


def test_nan_compares_equal_only_to_nan():
    a = np.array([[np.nan, 1.0], [0.0, np.inf]])
    b = np.array([[np.nan, np.nan], [0.0, np.inf]])
    assert abs_diff(a, b).tolist() == [[0.0, math.inf], [0.0, math.inf]]


# ------------------------------------------------------------------------------- republish


def drain(bus: can.BusABC, expected: int, timeout_s: float = 10.0) -> list[can.Message]:
    got: list[can.Message] = []
    deadline = time.monotonic() + timeout_s
    while len(got) < expected and time.monotonic() < deadline:
        msg = bus.recv(timeout=0.1)
        if msg is not None:
            got.append(msg)
    return got


@pytest.mark.parametrize(
    ("interface", "lockstep"),
    [("virtual", True), ("virtual", False), ("udp_multicast", False)],
)
def test_republish_sends_the_recorded_inputs(tmp_path, cfg, interface, lockstep):
    path = record_run(tmp_path / "small.mcap", cfg, 12, lockstep=lockstep)
    log = read_log(path)
    echo_id = ControllerCodec().encode_torque(0.0, 0.0).arbitration_id
    frames = [r for r in log.can_rx if r["arbitration_id"] != echo_id]
    payloads = [base64.b64decode(r["data"]) for r in log.vision]
    spec = isolated_spec(interface)
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    got: list[bytes] = []
    with open_bus(spec) as rx, open_session(cfg, listen=True, endpoint=endpoint) as hub:
        hub.subscribe(KEY_FEATURES, got.append)
        before_ns = time.monotonic_ns()
        result = republish_log(path, speed=0, can_spec=spec, zenoh_endpoint=endpoint, lead_in_s=0)
        after_ns = time.monotonic_ns()
        received = drain(rx, len(frames))
        assert wait_until(lambda: len(got) == len(payloads))
    assert result.can_frames == len(frames) and result.skipped == 1
    assert result.payloads == len(payloads) and not result.stopped
    # E2E bytes 0..7 as recorded; the SecOC trailer re-signed with the live key and fresh
    # freshness values, so a live receiver accepts every frame once
    assert [(m.arbitration_id, bytes(m.data[:8]).hex()) for m in received] == [
        (r["arbitration_id"], r["data"][:16]) for r in frames
    ]
    db = load_database()
    live = SecOCVerifier(rig_key(), "DSP")
    for m in received:
        data_id = db.by_id[m.arbitration_id].data_id
        assert live.check(m.arbitration_id, data_id, bytes(m.data)) is None
    if lockstep:
        assert got == payloads and result.restamped == 0
    else:
        assert result.restamped == len(payloads)
        # The recorded age at receipt (stamp to receive time) is kept and moved to the replay's
        # clock: each stamp lands inside the republish call, whatever the two clocks read.
        age_ns = STAMP_AGE_NS - VISION_RX_LEAD_NS
        for sent, orig in zip(got, payloads, strict=True):
            new, old = decode_features(sent), decode_features(orig)
            assert new._replace(stamp_ns=old.stamp_ns) == old
            assert before_ns <= new.stamp_ns + age_ns <= after_ns


def test_republish_cli_at_recorded_timing(tmp_path, cfg, capsys):
    path = record_run(tmp_path / "small.mcap", cfg, 5, lockstep=True)
    spec = isolated_spec("virtual")
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    got: list[bytes] = []
    with open_bus(spec) as rx, open_session(cfg, listen=True, endpoint=endpoint) as hub:
        hub.subscribe(KEY_FEATURES, got.append)
        argv = ["replay", str(path), "--republish", "--speed", "5", "--lead-in", "0", "--can", spec]
        assert main([*argv, "--zenoh-endpoint", endpoint, "--json"]) == 0
        out = json.loads(capsys.readouterr().out)
        assert len(drain(rx, out["can_frames"])) == out["can_frames"] > 0
        assert wait_until(lambda: len(got) == out["payloads"] == 4)
    assert out["skipped"] == 1 and out["stopped"] is False


def test_republish_stops_on_request_and_skips_empty_logs(tmp_path, cfg):
    import threading

    path = record_run(tmp_path / "small.mcap", cfg, 4, lockstep=True)
    stop = threading.Event()
    stop.set()
    spec = isolated_spec("virtual")
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    result = republish_log(
        path, speed=1, can_spec=spec, zenoh_endpoint=endpoint, wait_subscriber_s=0, stop=stop
    )
    assert result.stopped and result.can_frames == 0 and result.payloads == 0

    bare = tmp_path / "bare.mcap"
    with CycleRecorder(bare, cfg) as rec:
        rec.record_cycle({"tick": 0, "t_ns": 1, "u": [0.0, 0.0], "tau": [0.0, 0.0]})
    result = republish_log(bare, can_spec=spec, zenoh_endpoint=endpoint)
    assert result.can_frames == 0 and any("no raw inputs" in n for n in result.notes)


def test_help_lists_the_options(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["replay", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for option in ("--tol", "--out", "--set", "--json", "--republish", "--speed", "--can"):
        assert option in out


def test_out_never_overwrites_the_source(ioc_log, capsys):
    before = ioc_log.read_bytes()
    assert main(["replay", str(ioc_log), "--out", str(ioc_log)]) == 2
    assert "overwrite" in capsys.readouterr().err and ioc_log.read_bytes() == before
