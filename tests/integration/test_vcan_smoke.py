"""Smoke tests proving that a real SocketCAN ``vcan0`` works (python-can and can-utils).

Run them with ``scripts/vcan_pytest.py`` (native vcan0, else user-mode Linux); a plain
``pytest`` run skips them when the host has no vcan0.
"""

from __future__ import annotations

import queue
import subprocess
import threading
import time

import can
import pytest

from tests.support.vcan import VCAN_CHANNEL, requires_candump, requires_vcan

pytestmark = [pytest.mark.vcan, requires_vcan]

# Generous: user-mode Linux runs about 10x slower than the host.
RECV_TIMEOUT_S = 5.0


def _bus() -> can.BusABC:
    return can.Bus(interface="socketcan", channel=VCAN_CHANNEL)


def test_frame_travels_between_two_socketcan_buses() -> None:
    frames = [
        can.Message(arbitration_id=0x123, data=bytes([1, 2, 3, 4]), is_extended_id=False),
        can.Message(arbitration_id=0x1ABCDE, data=b"\xde\xad\xbe\xef\x00\x11\x22\x33"),
        can.Message(arbitration_id=0x7FF, data=b"", is_extended_id=False),
    ]
    with _bus() as rx, _bus() as tx:
        for frame in frames:
            tx.send(frame)
        for frame in frames:
            got = rx.recv(timeout=RECV_TIMEOUT_S)
            assert got is not None, f"frame 0x{frame.arbitration_id:X} not received"
            assert got.arbitration_id == frame.arbitration_id
            assert got.is_extended_id == frame.is_extended_id
            assert bytes(got.data) == bytes(frame.data)
            assert got.channel == VCAN_CHANNEL
        # The sender does not see its own frames (receive_own_messages defaults to False).
        assert tx.recv(timeout=0.05) is None


def _pump_lines(stream, sink: queue.Queue[str]) -> None:
    for line in iter(stream.readline, ""):
        sink.put(line.strip())


@requires_candump
def test_candump_sees_frames_sent_with_python_can() -> None:
    sync_id = 0x7F0
    payloads = {0x101: b"\x01", 0x102: b"\x02\x02", 0x18FF0001: b"\xca\xfe\xba\xbe"}
    expected = {
        f"{arb:03X}#{data.hex().upper()}" if arb <= 0x7FF else f"{arb:08X}#{data.hex().upper()}"
        for arb, data in payloads.items()
    }
    lines: queue.Queue[str] = queue.Queue()
    seen: list[str] = []
    with (
        subprocess.Popen(
            ["candump", "-L", VCAN_CHANNEL],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        ) as dump,
        _bus() as tx,
    ):
        reader = threading.Thread(
            target=_pump_lines, args=(dump.stdout, lines), name="candump-reader", daemon=True
        )
        try:
            reader.start()
            # candump gives no "ready" signal: send a sync frame until it shows up.
            deadline = time.monotonic() + 20 * RECV_TIMEOUT_S
            synced = False
            while not synced and time.monotonic() < deadline:
                assert dump.poll() is None, f"candump exited early: {seen}"
                tx.send(can.Message(arbitration_id=sync_id, data=b"", is_extended_id=False))
                try:
                    while True:
                        line = lines.get(timeout=0.2)
                        seen.append(line)
                        synced = synced or f" {VCAN_CHANNEL} {sync_id:03X}#" in line
                except queue.Empty:
                    pass
            assert synced, f"candump never printed the sync frame; output: {seen}"

            for arb, data in payloads.items():
                tx.send(can.Message(arbitration_id=arb, data=data, is_extended_id=arb > 0x7FF))
            deadline = time.monotonic() + RECV_TIMEOUT_S
            missing = set(expected)
            while missing and time.monotonic() < deadline:
                try:
                    line = lines.get(timeout=0.2)
                except queue.Empty:
                    continue
                seen.append(line)
                missing -= {frame for frame in missing if line.endswith(f" {frame}")}
            assert not missing, f"candump output lacks {sorted(missing)}; got {seen}"
            # Log format: "(seconds.micros) vcan0 ID#DATA"
            assert all(line.startswith("(") for line in seen if line)
        finally:
            dump.terminate()
            try:
                dump.wait(timeout=5)
            except subprocess.TimeoutExpired:
                dump.kill()
                dump.wait(timeout=5)
            if reader.is_alive():
                reader.join(timeout=5)  # ends at EOF on candump's stdout
