"""Two rigs on one CAN bus (one udp_multicast group and port, as two `hil up --lockstep --can
udp_multicast:GROUP:PORT` would): the DBC ids are the same, the keys differ (``hil up`` makes a
fresh key per run), so each rig sees the other's frames only as counted rejections (bad MAC)
and both converge as if alone (issue: |f| 525 and 1069 px, J 7852 and 11029).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from hal.bus import isolated_spec
from rt_controller.rig.options import RigOptions
from rt_controller.rig.processes import Rig
from tests.support import free_endpoint

pytestmark = pytest.mark.integration


def test_two_rigs_on_one_bus_converge_as_if_alone(tmp_path: Path) -> None:
    bus = isolated_spec("udp_multicast")  # one explicit GROUP:PORT for both
    rigs = [
        Rig(
            RigOptions(
                law="ioc",
                duration_s=10.0,
                lockstep=True,
                can=bus,
                zenoh_endpoint=free_endpoint(),
                log=tmp_path / f"rig{i}.mcap",
                extra_emulator=["--json"],
            )
        )
        for i in (1, 2)
    ]
    summaries = []
    try:
        for rig in rigs:
            rig.start()
        assert rigs[0].key_file != rigs[1].key_file
        assert rigs[0].key_file.read_bytes() != rigs[1].key_file.read_bytes()
        for rig in rigs:
            summaries.append(rig.wait_controller())
    finally:
        for rig in rigs:
            rig.close()
    for i, s in enumerate(summaries, 1):
        can_rx = s["rejections"]["can_rx"]
        print(
            f"RIG{i} | |f| {s['f_final_norm']:.3f} px | J {s['J']:.2f} | can_rx bad_mac "
            f"{can_rx['bad_mac']} | DSP rejected {s['rejections']['dsp_rejected_frames']} | "
            f"problems {s['problems']}"
        )
        assert s["f_final_norm"] < 1.0, s["f_final_norm"]
        assert 15.0 < s["J"] < 30.0, s["J"]  # the paper scenario's J (about 24), not 10^4
        assert s["dsp_faults"] == {} and s["watchdog_trips"] == 0 and not s["drive_ticks"]
        assert can_rx["bad_mac"] > 0, can_rx  # the other rig's DSP frames, counted
        assert can_rx["accepted"] > 0 and can_rx["counter_jump"] == 0, can_rx
        assert s["rejections"]["dsp_rejected_frames"] > 0  # the other rig's commands
        assert any("failed authentication" in p for p in s["problems"]), s["problems"]
