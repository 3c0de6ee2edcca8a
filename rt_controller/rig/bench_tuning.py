"""``hil bench tuning``: in a realtime run, how long a parameter set takes from the client's
request to the tick at which it is in force, and what a law switch rhc -> ioc -> rhc costs the
switching tick's decide phase.

The rig runs as ``hil up`` (realtime) in a child process; this process is the client (the signed
link of :mod:`rt_controller.calibration.link`, as ``hil param``). Latency = the outcome's
``t_ns`` (the loop's monotonic clock at the tick boundary; the same clock on this host) minus
the client's monotonic time just before it sent the request.
"""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hal.errors import HalTransportError
from hal.secoc import load_key_file, write_key_file
from hal.zenoh_session import ZenohSession, free_loopback_port, open_session
from rt_controller.calibration.link import request
from rt_controller.rig.bench_loop import bench_workdir
from rt_controller.rig.ending import ProcessEnd
from rt_controller.rig.failures import RigProcessDied
from rt_controller.rig.processes import Child
from rt_controller.rig.supervise import kill_with_stacks
from rt_controller.sample_stats import summary_stats

STARTUP_S = 120.0
"""How long the client waits for the rig to answer (its start-up on a loaded host)."""
TAIL_LINES = 20
"""How many of the rig's last stderr lines a failure carries."""
STOP_S = 60.0
"""How long ``hil up`` may take to stop its processes when the bench ends early."""
ENDING_S = 15.0
"""How long a client failure waits for ``hil up`` to end on its own: a rig whose controller
died is still stopping the others when the client's next request fails."""


def bench_tuning(
    workdir: Path | None = None, *, requests: int = 50, gap_s: float = 0.1
) -> dict[str, Any]:
    """Run the rig, make ``requests`` kp sets and one law switch rhc -> ioc -> rhc; the JSON.
    ``workdir``: keep the run's log and key there (default: a temporary folder, removed).
    A rig that ends before the figures raises :class:`RigProcessDied` with its stderr's tail."""
    duration = 20.0 + requests * (gap_s + 0.1)
    with contextlib.ExitStack() as stack:
        work = bench_workdir(stack, workdir, "hil-bench-tuning-")
        key_file = write_key_file(work / "bench.key", overwrite=True)
        ep = f"tcp/127.0.0.1:{free_loopback_port()}"
        log = work / "tuning.mcap"
        up = _start_up(stack, ep, key_file, log, duration)
        try:
            lat_ns, switch_ticks = _client(up.proc, ep, load_key_file(key_file), requests, gap_s)
            up.proc.wait(timeout=duration + 120)
        except Exception as exc:
            with contextlib.suppress(subprocess.TimeoutExpired):
                up.proc.wait(timeout=ENDING_S)
            if not up.proc.poll():  # running or ended cleanly: the client failed, not the rig
                raise
            raise _died(up) from exc
        finally:
            _stop(up)
        figures = _figures(up, log, lat_ns, switch_ticks)
        tail = up.tail(TAIL_LINES) if up.proc.returncode else ""
    kept = str(log) if workdir is not None else None
    return {**figures, "rig_exit": up.proc.returncode, "log": kept, "stderr_tail": tail}


def _start_up(
    stack: contextlib.ExitStack, ep: str, key_file: Path, log: Path, duration: float
) -> Child:
    """``hil up`` (realtime, rhc) as a child whose stdout and stderr go to files ``stack``
    closes, so its stderr's tail can say why it failed (a pipe nobody reads could block it)."""
    err = stack.enter_context(tempfile.TemporaryFile())  # noqa: SIM115 - the stack closes it
    out = stack.enter_context(tempfile.TemporaryFile())  # noqa: SIM115 - the stack closes it
    proc = subprocess.Popen(
        [sys.executable, "-m", "rt_controller.cli", "up", "--law", "rhc", "--duration",
         f"{duration:g}", "--zenoh-endpoint", ep, "--key-file", str(key_file), "--log", str(log),
         "--force", "--json"],  # the bench's own log in its workdir, as its key: replaced
        stdout=out, stderr=err,
    )  # fmt: skip
    return Child("rig (hil up)", proc, err, out)


def _stop(up: Child) -> None:
    """End a ``hil up`` still running (the bench failed or was interrupted) as Ctrl-C does: it
    stops its processes, controller first, and waits for them, so none outlives the bench nor
    writes into its removed folder (SIGKILL would orphan them). Killed after :data:`STOP_S`."""
    if up.proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            up.proc.send_signal(signal.SIGTERM)
        try:
            with contextlib.suppress(subprocess.TimeoutExpired):
                up.proc.wait(timeout=STOP_S)
        finally:  # also on a second Ctrl-C during the wait
            kill_with_stacks(up.proc)


def _died(up: Child) -> RigProcessDied:
    """The rig ended before the bench had its figures: its exit status and stderr's tail."""
    end = ProcessEnd(up.name, up.proc.returncode, time.monotonic_ns())
    return RigProcessDied(end, up.tail(TAIL_LINES))


def _client(
    up: subprocess.Popen, ep: str, key: bytes, requests: int, gap_s: float
) -> tuple[list[int], list[int]]:
    """As ``hil param``'s client: wait for the rig, time ``requests`` kp sets, switch the law
    rhc -> ioc -> rhc; (latencies in ns, the switching ticks)."""
    lat_ns: list[int] = []
    switch_ticks: list[int] = []
    deadline = time.monotonic() + STARTUP_S
    session = _connect(up, ep, deadline)
    try:
        while True:
            try:
                request(session, key, "get", timeout_s=1.0)
                break
            except Exception:
                if time.monotonic() > deadline or up.poll() is not None:
                    raise
        time.sleep(2.0)  # past arming
        for i in range(requests):
            kp = 0.13 + 0.001 * (i % 2)
            t0 = time.monotonic_ns()
            out = request(session, key, "set", changes={"gains.kp": kp}, timeout_s=10.0)
            lat_ns.append(int(out["outcome"]["t_ns"]) - t0)
            time.sleep(gap_s)
        for law in ("ioc", "rhc"):
            out = request(session, key, "set", changes={"controller.law": law})
            switch_ticks.append(int(out["outcome"]["tick"]))
            time.sleep(1.0)
    finally:
        session.close()
    return lat_ns, switch_ticks


def _connect(up: subprocess.Popen, ep: str, deadline: float) -> ZenohSession:
    """A client session to the rig's hub, waiting while ``hil up`` starts (longer than
    zenoh's default wait on a loaded host) and giving up as soon as it has ended."""
    while True:
        try:
            return open_session(listen=False, endpoint=ep, wait_s=2.0)
        except HalTransportError:
            if time.monotonic() > deadline or up.poll() is not None:
                raise


def _figures(up: Child, log: Path, lat_ns: list[int], switch_ticks: list[int]) -> dict[str, Any]:
    """:func:`tuning_figures` from the samples and the run's log; a failed rig without a
    readable log raises :class:`RigProcessDied` (its reason, not the log's)."""
    from rt_controller.logtools.reader import read_log

    try:
        loaded = read_log(log, raw=False)
    except Exception as exc:
        if up.proc.returncode:
            raise _died(up) from exc
        raise
    period_s = 1.0 / loaded.config.rates.control_hz if loaded.config else 0.02
    ticks = np.asarray(loaded.cycles["tick"])
    solve = np.asarray(loaded.cycles["solve_us"], dtype=float)
    return tuning_figures(lat_ns, switch_ticks, ticks, solve, period_s)


def tuning_figures(
    lat_ns: Sequence[int],
    switch_ticks: list[int],
    ticks: np.ndarray,
    solve_us: np.ndarray,
    period_s: float,
) -> dict[str, Any]:
    """The bench's figures from its samples: request-to-effect latency (ms and control periods)
    and the decide phase's time at the law switches against the other ticks; statistics of the
    finite samples (:mod:`rt_controller.sample_stats`), NaN when there are none."""
    at = [int(i[0]) for k in switch_ticks if (i := np.flatnonzero(ticks == k)).size]
    ms = summary_stats(np.asarray(lat_ns, dtype=float) / 1e6)
    ordinary = summary_stats(np.delete(solve_us, at), ("median", "p99"))
    return {
        "requests": len(lat_ns),
        "request_to_effect_ms": ms,
        "request_to_effect_periods": {k: ms[k] / 1e3 / period_s for k in ("median", "p99")},
        "within_two_periods": bool(ms["p99"] / 1e3 <= 2 * period_s),
        "law_switch": {
            "ticks": switch_ticks,
            "decide_us_at_switch": [float(solve_us[i]) for i in at],
            "decide_us_ordinary": ordinary,
        },
    }


__all__ = ["bench_tuning", "tuning_figures"]
