"""The controller daemon's real loop (read → decide → write → record) driven by a fake clock:
the emulated DSP on python-can's in-process ``virtual`` bus runs exactly up to each time the
clock jumps to, and a camera feeds features at 60 fps of that clock. Nothing sleeps, so the run
is deterministic whatever the machine does, and overruns are injected by advancing the clock
inside a tick.
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from hal.bus import isolated_spec, open_bus
from hal.config import RigConfig, load_config
from hal.joint_client import JointClient
from hal.vision_codec import FeatureMsg, encode_features
from hal.vision_receivers import FeatureDecoder
from plant_emulator.dsp_node import DspNode
from plant_emulator.dsp_realtime import RealtimeDsp
from rt_controller.logtools.reader import read_log
from rt_controller.runtime.daemon import ControllerDaemon, DaemonOptions
from tests.support.fake_clock import FakeClock

MS = 1_000_000
T0 = 5_000 * MS
FRAME_NS = round(1e9 / 60)


class RigClock(FakeClock):
    """Jumps to each deadline, running the DSP's 1 kHz service and a 60 fps camera on the way
    (the loop's wait work, the read-ahead, is not run: the client takes the frames off the bus
    as they arrive, see ``client``)."""

    def __init__(self, node: RealtimeDsp, start_ns: int) -> None:
        super().__init__(start_ns)
        self.node = node
        self.features: FeatureDecoder | None = None
        self.frame = 0
        self.next_frame = start_ns
        self.stall: tuple[int, int] | None = None
        """[from, to): the DSP process gets no CPU (a busy host); it catches up at ``to``."""
        self.client: JointClient | None = None
        """The controller's CAN client: frames are taken off the bus as they arrive and
        stamped then, as the kernel stamps a socket's frames (the daemon reads them later)."""
        node.start_realtime(start_ns)

    def watch(self, features: FeatureDecoder) -> None:
        """The camera starts, feeding ``features`` (the daemon's decoder)."""
        self.features = features
        self._camera()

    def _camera(self) -> None:
        _, _, f = self.node.world.measure()
        sim_ns = round(self.node.world.t * 1e9)
        msg = FeatureMsg(self.frame, self.t, sim_ns, 0, (float(f[0]), float(f[1])), True, False, 7)
        self.features.feed(encode_features(msg), self.t)
        self.frame += 1
        self.next_frame += FRAME_NS

    def advance(self, ns: int) -> None:
        """The controller works for ``ns``: the DSP and the camera go on meanwhile."""
        self.sleep_until(self.t + ns)

    def sleep_until(self, deadline_ns: int, idle=None) -> None:
        while self.t < deadline_ns:
            self.t = min(deadline_ns, self.t + MS)
            if self.stall is None or not self.stall[0] <= self.t < self.stall[1]:
                self.node.service(self.t)
                if self.client is not None:
                    self.client.drain(self.t)
            if self.features is not None and self.t >= self.next_frame:
                self._camera()


class NoZenoh:
    """A zenoh session stand-in: the fake clock's camera feeds the daemon's decoder itself."""

    class _Ring:
        def drain(self) -> list[bytes]:
            return []

        def close(self) -> None:
            pass

    class _Subscriber:
        def undeclare(self) -> None:
            pass

    class _Session:
        def declare_queryable(self, key: str, on_query: object) -> NoZenoh._Subscriber:
            """Nobody asks the ``hil param`` queryable of a fake-clock run."""
            return NoZenoh._Subscriber()

    session = _Session()

    def subscribe_ring(self, key: str) -> _Ring:
        return self._Ring()

    def subscribe(self, key: str, callback: object) -> _Subscriber:
        """Nothing arrives on it (the camera's images are not part of a fake-clock run)."""
        return self._Subscriber()


def run_daemon(
    tmp_path: Path,
    cfg: RigConfig,
    duration_s: float,
    slow_ticks: dict[int, int],
    dsp_stalls: frozenset[int] = frozenset(),
    on_tick=None,
    on_start=None,
):
    """Run the daemon (:meth:`ControllerDaemon.run` on given links, its log written by a recorder
    process) for ``duration_s`` of fake time;
    ``slow_ticks`` maps a tick number to extra nanoseconds its decide phase takes; for each
    tick in ``dsp_stalls`` the DSP gets no CPU from 4 ms before the next release to 2 ms after
    it, so the state it samples 3 ms before that release goes out 2 ms after it; ``on_start``
    is given the daemon before it runs. Returns (summary, log, node)."""
    spec = isolated_spec("virtual")
    log = tmp_path / "fake.mcap"
    period = cfg.rates.control_period_ns
    cfg = cfg.with_overrides({"transport.can": spec, "controller.clock": "realtime"})
    with open_bus(spec) as dsp_bus:
        node = RealtimeDsp(cfg, dsp_bus)
        clock = RigClock(node, T0)
        opts = DaemonOptions(
            duration_s=duration_s,
            log_path=log,
            realtime_settings=False,
            live=False,
            scene=False,
            clock=clock,
        )
        daemon = ControllerDaemon(cfg, opts, threading.Event())
        clock.watch(daemon.features)
        decide = daemon.controller.decide

        def slow_decide(*args, **kwargs):
            if on_tick is not None:
                on_tick(daemon.counters.ticks, node)
            if daemon.counters.ticks in dsp_stalls:  # the fake clock wakes on the release
                nxt = clock.t + period
                clock.stall = (nxt - 4 * MS, nxt + 2 * MS)
            extra = slow_ticks.get(daemon.counters.ticks)
            if extra:
                clock.advance(extra)  # this tick's work overruns
            return decide(*args, **kwargs)

        daemon.controller.decide = slow_decide
        if on_start is not None:
            on_start(daemon)
        with JointClient.open(spec, cfg) as dsp:
            clock.client = dsp
            summary = daemon.run((dsp, NoZenoh()))
    return summary, read_log(log), node


@pytest.fixture(scope="module")
def cfg() -> RigConfig:
    return load_config()


def test_a_clean_run_on_the_fake_clock(tmp_path, cfg):
    summary, log, node = run_daemon(tmp_path, cfg, 6.0, {})
    assert summary["ticks"] == 300 and summary["problems"] == []
    assert summary["deadline_misses"] == 0 and summary["missed_periods"] == 0
    c = log.cycles
    assert list(c["tick"]) == list(range(int(c["tick"][0]), int(c["tick"][0]) + 300))
    assert np.all(np.asarray(c["lateness_us"]) == 0.0)  # the fake clock wakes exactly on time
    assert set(c["law"]) == {"ioc"}
    assert np.hypot(*summary["f_final"]) < 5.0  # converged after the jump at 3 s
    assert node.stats.watchdog_trips == 0


def test_reruns_are_identical(tmp_path, cfg):
    a, log_a, _ = run_daemon(tmp_path / "a", cfg, 2.0, {})
    b, log_b, _ = run_daemon(tmp_path / "b", cfg, 2.0, {})
    assert a["J"] == b["J"] and a["f_final"] == b["f_final"]
    assert np.array_equal(np.asarray(log_a.cycles["tau"]), np.asarray(log_b.cycles["tau"]))


def test_an_overrun_skips_periods_and_is_reported(tmp_path, cfg):
    """Tick 100 takes 45 ms of a 20 ms period: it misses its deadline, the release at +20 ms is
    skipped (never run late in a burst), the next tick starts 5 ms late. With a watchdog of
    5 periods (100 ms) the 65 ms without a command does not trip it."""
    cfg = cfg.with_overrides({"dsp.watchdog_periods": 5})
    summary, log, node = run_daemon(tmp_path, cfg, 4.0, {100: 45 * MS})
    c = log.cycles
    ticks = np.asarray(c["tick"])
    i = int(np.flatnonzero(np.asarray(c["deadline_miss"]))[0])
    assert summary["deadline_misses"] == 1 and summary["missed_periods"] == 1
    assert ticks[i + 1] - ticks[i] == 2  # one release skipped
    assert int(c["missed_periods"][i + 1]) == 1
    assert float(c["lateness_us"][i + 1]) == 5000.0
    assert summary["watchdog_trips"] == 0 and node.stats.watchdog_trips == 0
    assert summary["problems"] == []


def test_an_overrun_past_the_watchdog_faults_the_dsp_and_fails_the_run(tmp_path, cfg):
    """Tick 100 overruns by 60 ms: 80 ms without a command (watchdog 3 periods = 60 ms): the
    DSP faults, the controller counts the trip, re-arms once (rearm_after_trip), the law runs
    again and the run is not clean."""
    summary, log, node = run_daemon(tmp_path, cfg, 4.0, {100: 60 * MS})
    assert node.stats.watchdog_trips == 1
    assert summary["watchdog_trips"] == 1 and summary["rearms"] == 1
    assert summary["dsp_faults"] == {"watchdog": 1}
    assert any("watchdog" in p for p in summary["problems"])
    laws = list(log.cycles["law"])
    assert "fault" in laws and laws[-1] == "ioc"  # re-armed, the law runs again


STALLS = frozenset(range(50, 80, 3))


def _reused(c) -> np.ndarray:
    """Per tick: whether it used exactly the previous tick's joint state (the arm is moving;
    angles and velocities both equal: a quantised velocity alone can repeat by chance)."""
    x = np.hstack([np.asarray(c["q"]), np.asarray(c["dq"])])
    return np.r_[False, np.all(x[1:] == x[:-1], axis=1)]


def test_a_late_state_is_counted_and_the_last_one_used(tmp_path, cfg):
    """A tick never waits for its input: every stalled period's tick reuses the previous state
    (its age compensated) and is counted, so a run shows how often the loop ran late data."""
    summary, log, _ = run_daemon(tmp_path, cfg, 2.0, {}, STALLS)
    assert summary["late_states"] == len(STALLS)
    assert np.count_nonzero(_reused(log.cycles)) == len(STALLS)
    assert np.asarray(log.cycles["read_us"]).max() == 0.0  # nothing waited


@pytest.mark.parametrize("rate", [50.0, 500.0])
def test_commands_flow_once_per_period_from_enable_on(tmp_path, cfg, rate):
    """The command stream is cyclic from the moment the DSP is armed, as a CiA 402 master's
    PDOs are: the release after ENABLE already carries a (zero) torque and every release after
    it one, so the DSP's watchdog (a few periods) never sees the hand-over from arming to the
    law as a gap. The fake clock wakes on time, so no gap exceeds one control period."""
    rated = cfg.with_overrides({"rates.control_hz": rate})
    period = rated.rates.control_period_ns
    seen: list[tuple[int, str]] = []  # (DSP clock, what) of each accepted frame
    handle = DspNode.handle

    def spy(node, msg, now_ns):
        before = node.last_cmd_ns
        out = handle(node, msg, now_ns)
        if node.last_cmd_ns != before:
            seen.append((now_ns, "torque" if out is not None else "enable"))
        return out

    DspNode.handle = spy
    try:
        summary, log, node = run_daemon(tmp_path, rated, 0.5, {})
    finally:
        DspNode.handle = handle
    enable = next(i for i, (_, what) in enumerate(seen) if what == "enable")
    times = np.array([t for t, _ in seen[enable:]])
    gaps = np.diff(times)
    assert gaps.size > 0 and gaps.max() <= period, (gaps.max(), period)
    assert summary["ticks"] == round(0.5 * rate) and summary["problems"] == []
    assert set(log.cycles["law"]) == {"ioc"}  # the first tick after arming runs the law
    assert node.stats.watchdog_trips == 0


def test_the_compiled_rules_time_is_recorded_apart_from_the_decide_phase(tmp_path, cfg):
    """``law_us``: the compiled per-tick rule alone (what ``hil bench solver``'s decide figures
    time), for every law; its own stopwatch (``solve_us`` is on the loop's clock, here fake)."""
    for law in ("rhc", "ioc"):
        run = cfg.with_overrides({"controller.law": law})
        summary, log, _ = run_daemon(tmp_path / law, run, 0.5, {})
        c = log.cycles
        assert set(c["law"]) == {law} and summary["problems"] == []
        assert np.all(np.asarray(c["law_us"]) > 0.0)


def test_a_second_trip_whose_statuses_arrive_in_one_read_is_still_re_armed(tmp_path, cfg):
    """Tick 100 overruns (trip 1); the next tick re-arms and overruns too, before the
    controller reads anything, so the DSP's reset, enabled and second-trip statuses all wait
    in the socket for one read. Judging the drive by the newest status alone saw "fault, then
    fault": no new trip, no re-arm, and the rest of the run held zero torque (a 500 Hz bench
    run sat 7 s in fault that way). Every status is fed to the drive monitor in order."""
    summary, log, node = run_daemon(tmp_path, cfg, 4.0, {100: 65 * MS, 101: 70 * MS})
    assert node.stats.watchdog_trips == 2
    assert summary["watchdog_trips"] == 2 and summary["rearms"] == 2
    laws = list(log.cycles["law"])
    assert laws[-1] == "ioc" and laws.count("fault") <= 4  # re-armed each time, law again


BUSY = frozenset(range(5, 250))
"""Every period from tick 5 on: the DSP's sample reaches the controller after its release."""


def test_a_loop_whose_states_come_a_period_late_acts_as_if_they_were_fresh(tmp_path, cfg):
    """A busy host: from tick 5 on the DSP process never gets the CPU in time to sample before
    the release, so every tick reads a state about 19 ms old. The paper's IOC gains do not
    tolerate a period of delay (``hil simulate --law ioc --state-delay 1 --no-predict`` ends
    far off target); the controller brings each state up to its tick with its nominal model
    and the torques it sent (``predict_ms``). The busy run then costs what a quiet one costs,
    and it stays clean through the target's jump; without the prediction it costs far more."""
    quiet, _, _ = run_daemon(tmp_path / "quiet", cfg, 5.0, {})
    busy, log, node = run_daemon(tmp_path / "busy", cfg, 5.0, {}, BUSY)
    c = log.cycles
    assert np.median(np.asarray(c["state_age_ms"])[10:]) > 15.0
    assert np.median(np.asarray(c["predict_ms"])[10:]) > 15.0  # about a period, compensated
    assert node.stats.faults == {} and busy["problems"] == []
    assert abs(busy["J"] - quiet["J"]) < 0.02 * quiet["J"]
    assert np.hypot(*busy["f_final"]) < 5.0  # converged after the jump at 3 s
    off = cfg.with_overrides({"controller.predict_state": False})
    blind, log, _ = run_daemon(tmp_path / "blind", off, 5.0, {}, BUSY)
    assert np.all(np.asarray(log.cycles["predict_ms"]) == 0.0)
    assert blind["J"] > 1.2 * quiet["J"]
