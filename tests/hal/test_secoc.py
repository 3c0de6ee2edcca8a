"""Rig keys and SecOC-style frame authentication (hal/secoc.py): key files, MAC, freshness,
the codecs' rejections by reason, authenticated vision messages, and the processes refusing to
run without a usable key."""

from __future__ import annotations

import os
import stat
import time
from pathlib import Path

import can
import pytest

from hal.can_codec import ControllerCodec, DspCodec
from hal.config import RigConfig
from hal.secoc import (
    FV_TX_MODULO,
    HalKeyError,
    SecOCSigner,
    SecOCVerifier,
    bench_mac,
    load_key_file,
    rebuild_fv,
    require_rig_key,
    write_key_file,
)
from hal.vision_codec import FeatureMsg, PoseMsg, encode_features, encode_pose
from hal.vision_receivers import FeatureDecoder, PoseDecoder
from rt_controller.cli import main

KEY_A, KEY_B = bytes(range(32)), bytes(range(1, 33))


def test_keygen_writes_a_0600_key_that_loads(tmp_path: Path, capsys) -> None:
    path = tmp_path / "rig.key"
    assert main(["keygen", str(path)]) == 0
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    key = load_key_file(path)
    assert len(key) == 32
    assert main(["keygen", str(path)]) == 2  # never silently replaced
    assert "already exists" in capsys.readouterr().err.strip().splitlines()[-1]
    assert main(["keygen", "--force", str(path)]) == 0
    assert load_key_file(path) != key


@pytest.mark.parametrize("mode", [0o640, 0o604, 0o644, 0o660])
def test_a_key_readable_by_group_or_others_is_refused(tmp_path: Path, mode: int) -> None:
    path = write_key_file(tmp_path / "rig.key")
    path.chmod(mode)
    with pytest.raises(HalKeyError, match="chmod 600"):
        load_key_file(path)


def test_missing_unreadable_or_malformed_keys_are_one_line(tmp_path: Path) -> None:
    with pytest.raises(HalKeyError, match=r"no such file.*hil keygen"):
        load_key_file(tmp_path / "nope.key")
    bad = tmp_path / "bad.key"
    bad.write_text("not hex\n")
    bad.chmod(0o600)
    with pytest.raises(HalKeyError, match="64 hex digits"):
        load_key_file(bad)
    with pytest.raises(HalKeyError, match="not a regular file"):
        load_key_file(tmp_path)
    if os.geteuid() != 0:  # root reads anything: the symlink below is the case root meets
        locked = write_key_file(tmp_path / "locked.key")
        locked.chmod(0o000)
        with pytest.raises(HalKeyError, match="cannot read"):
            load_key_file(locked)


def test_a_symlinked_key_cannot_be_read_even_by_root(tmp_path: Path) -> None:
    """The key is opened without following a symlink (another user's link could point it at
    any file): the open fails (ELOOP) for every user, root too, and says so in one line."""
    key = write_key_file(tmp_path / "real.key")
    load_key_file(key)  # the file itself is a good key
    link = tmp_path / "link.key"
    link.symlink_to(key)
    with pytest.raises(HalKeyError, match=r"link\.key: cannot read it: \S") as info:
        load_key_file(link)
    assert "\n" not in str(info.value)


def test_no_configured_key_tells_the_user_to_run_keygen(monkeypatch, capsys) -> None:
    monkeypatch.delenv("HIL_KEY_FILE", raising=False)
    with pytest.raises(HalKeyError, match="hil keygen"):
        require_rig_key(RigConfig(), "hil controller")
    assert main(["controller", "--duration", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "no rig key configured" in err[-1] and "hil keygen" in err[-1]


def test_processes_refuse_an_exposed_key(tmp_path: Path, capsys) -> None:
    path = write_key_file(tmp_path / "rig.key")
    path.chmod(0o644)
    assert main(["controller", "--key-file", str(path), "--duration", "1"]) == 2
    assert "chmod 600" in capsys.readouterr().err.strip().splitlines()[-1]


def test_freshness_is_rebuilt_across_the_wrap_of_the_transmitted_bits() -> None:
    ref = 5 * FV_TX_MODULO + 10
    assert rebuild_fv((ref - 20) % FV_TX_MODULO, ref) == ref - 20  # just before the wrap
    assert rebuild_fv((ref + 7) % FV_TX_MODULO, ref) == ref + 7
    ref = 5 * FV_TX_MODULO - 3
    assert rebuild_fv(2, ref) == 5 * FV_TX_MODULO + 2


def test_verifier_rejects_tampering_other_keys_replays_and_future_frames() -> None:
    now = [10**15]
    signer = SecOCSigner(KEY_A, "DSP", clock_us=lambda: now[0])
    ok = SecOCVerifier(KEY_A, "DSP", clock_us=lambda: now[0])
    other = SecOCVerifier(KEY_B, "DSP", clock_us=lambda: now[0])
    wrong_role = SecOCVerifier(KEY_A, "Controller", clock_us=lambda: now[0])
    head = bytes(range(8))
    f1, f2 = signer.sign(0x2002, head), signer.sign(0x2002, head)
    assert other.check(0x180, 0x2002, f1) == "bad_mac"
    assert wrong_role.check(0x180, 0x2002, f1) == "bad_mac"  # per-node keys
    assert ok.check(0x180, 0x2003, f1) == "bad_mac"  # data id is authenticated
    tampered = bytearray(f1)
    tampered[5] ^= 1
    assert ok.check(0x180, 0x2002, tampered) == "bad_mac"
    assert ok.check(0x180, 0x2002, f2) is None
    assert ok.check(0x180, 0x2002, f1) == "stale_freshness"  # older than one accepted
    assert ok.check(0x180, 0x2002, f2) == "stale_freshness"  # replayed
    fresh_rx = SecOCVerifier(KEY_A, "DSP", clock_us=lambda: now[0])
    now[0] += 3_000_000  # 3 s later a new receiver sees an old authentic frame
    assert fresh_rx.check(0x180, 0x2002, f2) == "stale_freshness"
    future = SecOCSigner(KEY_A, "DSP", clock_us=lambda: now[0] + 5_000_000).sign(0x2002, head)
    assert ok.check(0x180, 0x2002, future) == "future_freshness"
    assert SecOCVerifier(KEY_B, "DSP", verify=False).check(0x180, 0x2002, f1) is None


def test_freshness_is_judged_at_arrival_so_a_busy_receiver_keeps_queued_frames() -> None:
    now = [10**15]
    signer = SecOCSigner(KEY_A, "DSP", clock_us=lambda: now[0])
    rx = SecOCVerifier(KEY_A, "DSP", clock_us=lambda: now[0])
    head = bytes(range(8))
    queued = signer.sign(0x2002, head)
    arrived = now[0]
    now[0] += 5_000_000  # the receiver reads it 5 s later (busy host): judged at arrival
    assert rx.check(0x180, 0x2002, queued, rx_us=arrived) is None
    # a replay of an old authentic frame arrives now: stale at its own arrival
    old = SecOCSigner(KEY_A, "DSP", clock_us=lambda: now[0] - 3_000_000).sign(0x2003, head)
    assert rx.check(0x181, 0x2003, old, rx_us=now[0]) == "stale_freshness"
    # a stamp later than the receiver's clock is not believed: the clock is used instead
    late = SecOCSigner(KEY_A, "DSP", clock_us=lambda: now[0] - 3_000_000).sign(0x2004, head)
    assert rx.check(0x182, 0x2004, late, rx_us=now[0] + 10**9) == "stale_freshness"
    assert rx.check(0x183, 0x2004, late, rx_us=0) == "stale_freshness"


def test_codec_judges_freshness_at_the_frames_receive_stamp() -> None:
    """The codec hands the bus's receive stamp to the verifier: a frame signed now but stamped
    as arrived 10 s ago is judged at that arrival (its freshness is then 10 s in the future);
    the same frame unstamped, or stamped later than the clock, is judged now and accepted."""
    ctl = ControllerCodec(key=KEY_A)
    for stamp, verdict in ((time.time() - 10.0, "future"), (0.0, "ok"), (time.time() + 60, "ok")):
        msg = ctl.encode_torque(1.0, 2.0)
        msg.timestamp = stamp
        dsp = DspCodec(key=KEY_A)
        accepted = dsp.decode(msg) is not None
        assert accepted == (verdict == "ok")
        assert dsp.stats.future_freshness == (verdict == "future")


def test_codecs_of_different_rigs_do_not_understand_each_other() -> None:
    ctl_a, dsp_a, dsp_b = ControllerCodec(key=KEY_A), DspCodec(key=KEY_A), DspCodec(key=KEY_B)
    msg = ctl_a.encode_torque(100.0, 10.0)
    assert dsp_b.decode(msg) is None and dsp_b.stats.bad_mac == 1
    assert dsp_a.decode(msg) is not None
    assert dsp_a.decode(msg) is None and dsp_a.stats.stale_freshness == 1
    resigned = ControllerCodec(key=KEY_B).sign(msg)  # re-signed: bytes 0..7 kept
    assert bytes(resigned.data[:8]) == bytes(msg.data[:8])
    assert dsp_b.decode(resigned) is not None
    classic = can.Message(arbitration_id=0x100, data=bytes(msg.data[:8]), is_extended_id=False)
    assert dsp_a.decode(classic) is None and dsp_a.stats.wrong_length == 1  # unauthenticated


def test_offline_decoding_skips_authentication() -> None:
    msg = ControllerCodec(key=KEY_A).encode_torque(1.0, 2.0)
    offline = DspCodec(key=KEY_B, verify=False)
    assert offline.decode(msg) is not None


def test_features_and_poses_from_another_key_are_counted_bad_mac() -> None:
    feat = FeatureMsg(1, 0, 0, 0, (1.0, 2.0), True, True, 7)
    dec = FeatureDecoder(max_age_ns=None, key=KEY_A)
    assert dec.feed(encode_features(feat, KEY_B)) is None
    assert dec.counts.bad_mac == 1 and dec.counts.rejected == 1 and dec.counts.untrusted == 1
    assert dec.source is None  # a forged message never locks the source
    assert dec.feed(encode_features(feat, KEY_A)) is not None
    pose = PoseMsg(1, 0, 0, 0.1, 0.2, 0.3, True, 9)
    pdec = PoseDecoder(key=KEY_A)
    assert pdec.feed(encode_pose(pose, KEY_B)) is None and pdec.counts.bad_mac == 1
    assert pdec.feed(encode_pose(pose, KEY_A)) is not None
    # a features MAC never verifies as a pose (labels differ) even with the same key
    body = encode_features(feat, KEY_A)
    assert body[-16:] != encode_pose(pose, KEY_A)[-16:]


def test_bench_mac_reports_sign_and_verify_cost() -> None:
    out = bench_mac(200)
    assert set(out) == {"secoc_sign_us", "secoc_verify_us"}
    assert all(v > 0 for v in out.values())
