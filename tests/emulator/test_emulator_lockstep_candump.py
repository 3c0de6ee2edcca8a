"""``hil emulator --lockstep`` as a process over a real transport, answered by a test client:
two runs are bit-identical, and on vcan0 every frame ``candump`` records decodes with the DBC.

* The ``socketcan`` case is marked ``vcan``: run it with ``scripts/vcan_pytest.py`` (a native
  vcan0, else user-mode Linux); ``candump`` from can-utils runs in the same kernel and its frames
  must decode with the DBC and pass the E2E CRC (the decoded lines are printed: run with ``-s``
  to see them).
* The ``udp_multicast`` case (host-local, isolated port) is marked ``integration`` and runs
  natively everywhere.

The emulator process helpers and the transports are in ``tests/support/emulator_proc.py``.
"""

from __future__ import annotations

import json
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import cantools
import pytest

from hal.can_database import DBC_PATH
from hal.config import RigConfig
from hal.errors import HalTimeoutError
from hal.joint_client import JointClient
from tests.support import e2e_crc_reference
from tests.support.emulator_proc import (
    RECV_TIMEOUT_S,
    SLOW,
    STOP_TIMEOUT_S,
    TEST_TIMEOUT_S,
    Proc,
    emulator,
)
from tests.support.vcan import (
    LOCKSTEP_REPLY_TOML,
    VCAN_CHANNEL,
    candump_available,
    vcan_required,
)

pytestmark = pytest.mark.timeout(TEST_TIMEOUT_S)

DB = cantools.database.load_file(str(DBC_PATH))
DATA_IDS = {m.frame_id: int(m.dbc.attributes["E2EDataID"].value) for m in DB.messages}


def decode_candump_line(line: str) -> tuple[str, dict[str, Any]] | None:
    """``(1700000000.123456) vcan0 180#A1B2...`` -> (message name, signals), None if not ours."""
    parts = line.split()
    if len(parts) != 3 or "#" not in parts[2]:
        return None
    ident, _, data_hex = parts[2].partition("#")
    if data_hex.startswith("#"):  # CAN FD: "ID##<flags nibble><data>"
        data_hex = data_hex[2:]
    frame_id = int(ident, 16)
    if len(ident) > 3 or frame_id not in DATA_IDS:
        return None
    data = bytes.fromhex(data_hex)
    msg = DB.get_message_by_frame_id(frame_id)
    assert len(data) == 16, line  # CAN FD: E2E bytes 0..7, freshness, truncated MAC
    assert e2e_crc_reference(DATA_IDS[frame_id], data[:8]) == data[0], f"bad E2E CRC: {line}"
    return msg.name, msg.decode(data, decode_choices=False)


def lockstep_process_run(cfg: RigConfig, spec: str, periods: int, config: Path) -> dict[str, Any]:
    """``hil emulator --lockstep --duration --config CONFIG`` answered by a JointClient (PD
    law); its summary."""
    duration = periods / cfg.rates.control_hz
    args = ("--no-vision-link", "--lockstep", "--duration", f"{duration}", "--config", str(config))
    with (
        emulator(spec, *args) as emu,
        JointClient.open(spec, cfg) as client,
    ):
        client.enable()
        answered: set[int] = set()
        while len(answered) < periods:
            try:
                k = client.wait_sync(timeout=RECV_TIMEOUT_S)
            except HalTimeoutError:
                pytest.fail(f"no Sync after {sorted(answered)}; stderr {emu.err}")
            if k in answered:
                continue  # a re-sent Sync(k): already answered
            state = client.latest_state(max_age_s=1e9)
            tau1 = 20.0 * (0.9 - state.q[0]) - 2.0 * state.dq[0]
            client.send_torque(tau1, 0.5, tick=k)
            answered.add(k)
        rc = emu.popen.wait(timeout=STOP_TIMEOUT_S)  # --duration: it ends by itself
        client.disable()
        emu.close()
    assert rc == 0, emu.err
    summary = json.loads(emu.out[-1])
    assert summary["mode"] == "lockstep"
    substeps = round(cfg.rates.physics_hz / cfg.rates.control_hz)
    assert summary["physics_steps"] == periods * substeps
    assert summary["missing_periods"] == 0
    assert summary["rejected"]["rejected"] == 0
    return summary


def test_lockstep_emulator_process(cfg: RigConfig, can_spec: str, tmp_path: Path) -> None:
    """Lockstep over a real transport, twice: bit-identical runs. On vcan0, candump (same
    kernel) records the run and every frame must decode with the DBC and pass the E2E CRC."""
    periods = 20
    config = tmp_path / "rig.toml"
    config.write_text(LOCKSTEP_REPLY_TOML, encoding="utf-8")
    socketcan = can_spec.startswith("socketcan")
    dump: Proc | None = None
    if socketcan:
        if not candump_available():
            if vcan_required():
                pytest.fail("candump not found: the vcan tests need can-utils")
            pytest.skip("candump not found (sudo apt-get install can-utils)")
        dump = Proc(["candump", "-L", VCAN_CHANNEL])
    try:
        if dump is not None:
            # candump gives no ready signal; start it well before the emulator's first frame.
            time.sleep(0.5 * SLOW)
            assert dump.popen.poll() is None, f"candump exited: {dump.err}"
        first = lockstep_process_run(cfg, can_spec, periods, config)
        if dump is not None:
            time.sleep(0.5 * SLOW)  # let candump print the last frames
    finally:
        if dump is not None:
            dump.close()
    second = lockstep_process_run(cfg, can_spec, periods, config)
    print(f"lockstep: q after {periods} periods {first['q']} (run 1) {second['q']} (run 2)")
    assert first["q"] == second["q"] and first["dq"] == second["dq"]
    assert first["q"][0] > cfg.scenario.q0[0]
    if dump is None:
        return
    decoded: list[tuple[str, str, dict[str, Any]]] = []
    for line in dump.out:
        got = decode_candump_line(line)
        if got is not None:
            decoded.append((line, *got))
    decoded.sort(key=lambda d: d[0])  # by candump's timestamp
    print(f"candump -L {VCAN_CHANNEL}: {len(dump.out)} lines, decoded with {DBC_PATH.name}:")
    shown = decoded[:14]  # the start of the run, plus one frame of every other message
    for name in sorted({d[1] for d in decoded} - {d[1] for d in shown}):
        shown.append(next(d for d in decoded if d[1] == name))
    for line, name, signals in shown:
        text = ", ".join(
            f"{k}={v:.6g}" if isinstance(v, float) else f"{k}={v}" for k, v in signals.items()
        )
        print(f"  {line}\n      {name}: {text}")
    by_name: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for _, name, signals in decoded:
        by_name[name].append(signals)
    assert len(decoded) == len(dump.out), "candump printed frames that are not in the DBC"
    for name in ("Sync", "TorqueCommand", "DspControl", "JointPosition", "JointVelocity",
                 "DspStatus"):  # fmt: skip
        assert by_name[name], f"candump saw no {name}"
    assert sorted({s["Tick"] for s in by_name["Sync"]}) == list(range(periods))
    assert {s["Tick"] for s in by_name["TorqueCommand"]} >= set(range(periods))
