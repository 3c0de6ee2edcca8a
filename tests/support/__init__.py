"""Helpers shared by the test modules (importable because pytest puts the repository root on
``sys.path``: ``pythonpath = ["."]`` in pyproject.toml).

Sub-modules: :mod:`tests.support.vcan` (SocketCAN markers), :mod:`tests.support.proc` (finding
processes a test started).
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from hal.zenoh_session import free_loopback_port

REPO = Path(__file__).resolve().parents[2]
"""The repository root."""


def crc_reference(data: bytes) -> int:
    """Bitwise CRC-8 SAE J1850 (poly 0x1D, init 0xFF, xor-out 0xFF), independent of hal."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF


def e2e_crc_reference(data_id: int, payload: bytes) -> int:
    """The E2E CRC of a frame: over the data id (little endian) and payload bytes 1..7."""
    return crc_reference(bytes([data_id & 0xFF, data_id >> 8]) + bytes(payload[1:8]))


def command_is_malformed(data: bytes) -> bool:
    """Whether a DspControl payload (bytes 0..7) is a decode error, read from the DBC's layout
    independently of hal: Command (byte 2) outside 1..4."""
    return data[2] not in range(1, 5)


def session_key() -> bytes:
    """The test session's rig key (``$HIL_KEY_FILE``, set by tests/conftest.py), read
    independently of hal."""
    return bytes.fromhex(Path(os.environ["HIL_KEY_FILE"]).read_text().strip())


class SecocReference:
    """The SecOC verdict a receiver must give (MAC, then freshness; docs/concepts/secoc.md), with
    its own model of the last accepted freshness per frame id; independent of hal."""

    def __init__(self, key: bytes | None = None) -> None:
        self.key = key if key is not None else session_key()
        self.last_fv: dict[int, int] = {}

    def verdict(self, fid: int, sender: str, data_id: int, data: bytes) -> str | None:
        now = time.time_ns() // 1000
        low = int.from_bytes(data[8:12], "little")
        candidates = (((now >> 32) + k) << 32 | low for k in (-1, 0, 1))
        fv = min(candidates, key=lambda v: abs(v - now))
        if secoc_tag_reference(self.key, sender, data_id, fv, data[:8]) != data[12:16]:
            return "bad_mac"
        if fv <= self.last_fv.get(fid, -1) or fv < now - 2_000_000:
            return "stale_freshness"
        if fv > now + 1_000_000:
            return "future_freshness"
        self.last_fv[fid] = fv
        return None


def secoc_tag_reference(key: bytes, sender: str, data_id: int, fv: int, head: bytes) -> bytes:
    """The 32-bit SecOC MAC of a CAN frame (docs/concepts/secoc.md), independent of hal."""
    import hashlib
    import hmac

    node_key = hmac.new(key, b"hil-secoc-v1\0hil/can/" + sender.encode(), hashlib.sha256).digest()
    msg = data_id.to_bytes(2, "little") + fv.to_bytes(8, "little") + bytes(head[:8])
    return hmac.new(node_key, msg, hashlib.sha256).digest()[:4]


def wait_until(pred: Callable[[], object], timeout_s: float = 10.0, poll_s: float = 0.005) -> bool:
    """Poll ``pred`` until it is true (True) or ``timeout_s`` passes (False)."""
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            return False
        time.sleep(poll_s)
    return True


def free_endpoint() -> str:
    """A zenoh endpoint on a free loopback TCP port."""
    return f"tcp/127.0.0.1:{free_loopback_port()}"


def hil_command() -> list[str]:
    """How to run the ``hil`` console script of this interpreter's environment."""
    script = Path(sys.executable).with_name("hil")
    return [str(script)] if script.exists() else [sys.executable, "-m", "rt_controller.cli"]


def start_hil(args: list[str], capture: bool = False) -> subprocess.Popen:
    """``hil ARGS`` in the background from the repository root, in a session of its own (its
    children with it), output discarded (``capture``: piped, as text); end it with
    :func:`stop_hil`."""
    out = subprocess.PIPE if capture else subprocess.DEVNULL
    return subprocess.Popen(
        [*hil_command(), *args],
        stdout=out,
        stderr=out,
        text=capture,
        start_new_session=True,
        cwd=REPO,
    )


def stop_hil(proc: subprocess.Popen) -> None:
    """SIGTERM to the session of a :func:`start_hil` process, SIGKILL after 15 s; reaped."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:  # pragma: no cover - only on a hang
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def run_hil(args: list[str], timeout_s: float) -> subprocess.CompletedProcess[str]:
    """Run ``hil ARGS`` from the repository root in its own session; on a hang, kill the whole
    session (the rig's children too) and re-raise ``TimeoutExpired``."""
    proc = subprocess.Popen(
        [*hil_command(), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        cwd=REPO,
    )
    try:
        out, err = proc.communicate(timeout=timeout_s)
    finally:
        if proc.poll() is None:  # pragma: no cover - only on a hang
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def start_hil_up(endpoint: str, log: Path, *extra: str) -> subprocess.Popen:
    """``hil up`` on a private CAN bus and zenoh endpoint, in a session of its own (so a test
    can signal it alone), with text pipes for its output."""
    from hal.bus import isolated_spec

    args = [sys.executable, "-m", "rt_controller.cli", "up"]
    args += ["--can", isolated_spec("udp_multicast"), "--zenoh-endpoint", endpoint]
    return subprocess.Popen(
        [*args, "--log", str(log), *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        cwd=REPO,
    )


def cycles_logged(log: Path) -> int:
    """Cycles in a log that is still being written (0 while it is not readable yet)."""
    from rt_controller.logtools.reader import read_log

    try:
        return read_log(log, raw=False).n_cycles
    except Exception:
        return 0


def nominal_rk4(model, q, dq, tau, dt):
    """One classic RK4 step of the controller's nominal model (an implementation independent of
    the emulator's physics, see tests/integration/test_physics_crosscheck.py)."""
    from tests.support.nominal_model import NumpyModel

    m = NumpyModel.of(model)

    def acc(q, dq):
        return np.linalg.solve(m.M(q), tau - m.C(q, dq) @ dq - m.g(q))

    k1q, k1v = dq, acc(q, dq)
    k2q, k2v = dq + 0.5 * dt * k1v, acc(q + 0.5 * dt * k1q, dq + 0.5 * dt * k1v)
    k3q, k3v = dq + 0.5 * dt * k2v, acc(q + 0.5 * dt * k2q, dq + 0.5 * dt * k2v)
    k4q, k4v = dq + dt * k3v, acc(q + dt * k3q, dq + dt * k3v)
    return (
        q + dt / 6 * (k1q + 2 * k2q + 2 * k3q + k4q),
        dq + dt / 6 * (k1v + 2 * k2v + 2 * k3v + k4v),
    )


@contextlib.contextmanager
def killed_once_ticking(log: Path, victim: str, ticks: int) -> Iterator[None]:
    """While inside: SIGKILL this process's child running ``hil VICTIM`` once ``log`` holds
    ``ticks`` cycle records (nothing if the block ends first)."""
    from tests.support.proc import child_running

    done = threading.Event()

    def kill_when_ticking() -> None:
        while not done.is_set() and cycles_logged(log) < ticks:
            time.sleep(0.05)
        pid = child_running(os.getpid(), victim)
        if pid is not None and not done.is_set():
            os.kill(pid, signal.SIGKILL)

    killer = threading.Thread(target=kill_when_ticking, daemon=True)
    killer.start()
    try:
        yield
    finally:
        done.set()
        killer.join()


def error_line(argv: list[str], capsys: Any) -> str:
    """``hil ARGV`` in-process ends in status 2 and one ``error:`` line on stderr, never a
    traceback; the line (``capsys``: pytest's fixture)."""
    from rt_controller.cli import main

    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if "error:" in ln]
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, (code, err)
    return lines[0]
