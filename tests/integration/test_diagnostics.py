"""Every rejection counter reaches the log (``/diagnostics``), the controller's summary and
``hil report``, and all three count the same things the same way.

The integration test injects known numbers of bad inputs into a live rig: CAN frames with a
broken CRC on the rig's bus and malformed vision payloads on its zenoh key.
"""

from __future__ import annotations

import json
import time

import can
import pytest

from hal.bus import isolated_spec, open_bus
from hal.can_codec import DspCodec
from hal.config import load_config
from hal.zenoh_session import KEY_FEATURES, free_loopback_port, open_session
from rt_controller.logtools.deadline_report import summarize
from rt_controller.logtools.reader import read_log
from rt_controller.rig.options import RigOptions
from rt_controller.rig.processes import Rig
from rt_controller.runtime import diagnostics
from rt_controller.runtime.recorder import DIAGNOSTICS_TOPIC, CycleRecorder

BAD_CAN = 25
BAD_FEATURES = 7


def test_build_levels_and_messages():
    rec = diagnostics.build(
        t_ns=5,
        tick=50,
        can_rx={"accepted": 10, "bad_crc": 2, "rejected": 2},
        features={"accepted": 3, "bad_size": 1, "stale_age": 1},
        dsp={"torque_enabled": True, "watchdog_tripped": False},
        controller={"ticks": 50, "deadline_misses": 0, "watchdog_trips": 0},
        recorder={"dropped": 3, "encode_errors": 0},
    )
    by = {s["name"]: s for s in rec["status"]}
    assert [s["name"] for s in rec["status"]] == [
        "can_rx",
        "features",
        "dsp",
        "controller",
        "recorder",
    ]
    assert by["can_rx"]["level"] == diagnostics.WARN and by["can_rx"]["message"].startswith("2 ")
    assert by["features"]["message"] == "2 message(s) rejected"
    assert by["dsp"]["level"] == diagnostics.OK and by["dsp"]["message"] == "armed"
    assert by["recorder"]["level"] == diagnostics.ERROR and rec["level"] == diagnostics.ERROR
    assert diagnostics.values_of(rec, "can_rx")["bad_crc"] == 2


def test_diagnostics_round_trip_through_the_log(tmp_path):
    cfg = load_config()
    path = tmp_path / "d.mcap"
    record = diagnostics.build(
        t_ns=1,
        tick=0,
        can_rx={"rejected": 0},
        features={},
        dsp={},
        controller={},
        recorder={},
        final=True,
    )
    with CycleRecorder(path, cfg) as rec:
        rec.record_cycle({"tick": 0, "t_ns": 1, "u": [0.0, 0.0], "tau": [0.0, 0.0]})
        assert rec.record_diagnostics(record, final=True)
    log = read_log(path, raw=False)
    assert log.diagnostics == [json.loads(json.dumps(record))]
    assert log.schemas[DIAGNOSTICS_TOPIC] == "hil.Diagnostics"


def _inject(can_spec: str, endpoint: str, cfg) -> None:
    """Bad CAN frames (valid id and length, a byte flipped: the MAC fails) and malformed
    feature payloads."""
    good = DspCodec().encode_state((0.1, 0.2), (0.0, 0.0), 0)[0]
    data = bytearray(good.data)
    data[0] ^= 0xFF  # CRC byte: the MAC (checked first) fails
    with open_bus(can_spec) as bus:
        for _ in range(BAD_CAN):
            bus.send(
                can.Message(
                    arbitration_id=good.arbitration_id,
                    data=bytes(data),
                    is_extended_id=False,
                    is_fd=True,
                )
            )
    with open_session(cfg, listen=False, endpoint=endpoint) as s:
        pub = s.publisher(KEY_FEATURES)
        for _ in range(BAD_FEATURES):
            pub.put(b"\x00\x01garbage")
        time.sleep(0.5)  # let zenoh deliver before the session closes
        pub.undeclare()


@pytest.mark.integration
def test_injected_rejections_are_counted_alike_in_summary_log_and_report(tmp_path):
    cfg = load_config()
    log = tmp_path / "diag.mcap"
    ep = f"tcp/127.0.0.1:{free_loopback_port()}"
    spec = isolated_spec("udp_multicast")
    opts = RigOptions(law="ioc", duration_s=6.0, can=spec, zenoh_endpoint=ep, log=log)
    with Rig(opts) as rig:
        rig.start()
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:  # wait until the controller runs
            try:
                if read_log(log, raw=False).n_cycles >= 10:
                    break
            except Exception:
                pass
            time.sleep(0.05)
        _inject(spec, ep, cfg)
        summary = rig.wait_controller()
    can_rx = summary["rejections"]["can_rx"]
    features = summary["rejections"]["features"]
    assert can_rx["bad_mac"] == BAD_CAN, can_rx  # a loaded host may add others (e.g. stale)
    malformed = sum(v for k, v in features.items() if k.startswith("bad_"))
    assert malformed == BAD_FEATURES, features
    loaded = read_log(log, raw=False)
    final = loaded.diagnostics[-1]
    assert final["final"] and len(loaded.diagnostics) >= 2
    assert diagnostics.values_of(final, "can_rx") == can_rx
    assert diagnostics.values_of(final, "features") == features
    report = summarize(loaded)
    diag = report["diagnostics"]
    assert diag["can_rx_rejected"] == can_rx["rejected"]
    assert diag["features_rejected"] == diagnostics.rejected(features)
    assert diag["can_rx_by_reason"]["bad_mac"] == BAD_CAN
    assert report["stale_features"] == summary["stale_features"]
    assert report["stale_state"] == summary["stale_states"]
    assert report["fallbacks"] == summary["fallbacks"]
