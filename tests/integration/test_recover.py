"""``hil recover``: a cut log (recorder SIGKILLed, file cut at any byte) becomes a finished copy
that mcap's own indexed reader opens, holding exactly the messages of the complete records.

The logs are real: a lockstep ``hil up`` run, and a recorder process killed with SIGKILL.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

pytestmark = pytest.mark.integration

HIL = str(Path(sys.executable).parent / "hil")


def hil(*argv: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [HIL, *map(str, argv)], capture_output=True, text=True, timeout=300, check=False
    )


def stock_messages(path: Path) -> list[tuple[str, int, bytes]]:
    """Every message through mcap's indexed reader (summary and chunk indexes), by log time."""
    with path.open("rb") as fh:
        reader = make_reader(fh)
        assert reader.get_summary() is not None
        return [(ch.topic, m.log_time, m.data) for _, ch, m in reader.iter_messages()]


def stream_messages(data: bytes, upto: int | None = None) -> list[tuple[str, int, bytes]]:
    """The messages of a finished log in file order, through the sequential reader; with
    ``upto``, those of the records (a message's chunk) that end by that offset."""
    from io import BytesIO

    fh = BytesIO(data)
    topics: dict[int, str] = {}
    out = []
    for rec in StreamReader(fh).records:
        if type(rec).__name__ == "Channel":
            topics[rec.id] = rec.topic
        elif type(rec).__name__ == "Message" and (upto is None or fh.tell() <= upto):
            out.append((topics[rec.channel_id], rec.log_time, rec.data))
        elif type(rec).__name__ == "DataEnd":
            break
    return out


def by_time(msgs: list[tuple[str, int, bytes]]) -> list[tuple[str, int, bytes]]:
    return sorted(msgs, key=lambda m: (m[1], m[0], m[2]))


@pytest.fixture(scope="module")
def rig_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rig") / "run.mcap"
    done = hil("up", "--lockstep", "--duration", "2", "--wall-timeout", "60", "--log", path)
    assert path.exists() and "Traceback" not in done.stderr, done.stderr  # clean or not: a log
    return path


def recover(log: Path, out: Path) -> dict:
    done = hil("recover", log, "--out", out, "--json")
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    return json.loads(done.stdout)


@pytest.mark.parametrize("fraction", [0.1, 0.35, 0.6, 0.85, 0.999])
def test_a_log_cut_anywhere_becomes_a_log_the_stock_reader_opens(rig_log, tmp_path, fraction):
    data = rig_log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises((McapError, ValueError, EOFError)), cut.open("rb") as fh:
        list(make_reader(fh).iter_messages())  # the stock reader cannot open the cut log
    out = tmp_path / "recovered.mcap"
    if not stream_messages(data, upto=len(cut.read_bytes())):  # cut inside the first chunk
        done = hil("recover", cut, "--out", out, "--json")
        assert done.returncode == 1 and "nothing to recover" in done.stderr, done.stderr
        assert len(done.stderr.splitlines()) == 1 and not out.exists(), done.stderr
        return
    res = recover(cut, out)
    got = stock_messages(out)
    assert len(got) == res["messages"]
    # exactly the messages of the complete records before the cut, nothing lost or invented
    assert by_time(got) == by_time(stream_messages(data, upto=len(cut.read_bytes())))
    assert not res["finished"] and res["lost_bytes"] == len(cut.read_bytes()) - res["kept_bytes"]
    assert res["lost_bytes"] > 0
    with out.open("rb") as fh:
        reader = make_reader(fh)
        assert reader.get_summary().statistics.message_count == len(got)
        names = [m.name for m in reader.iter_metadata()]
    assert {"hil.config", "hil.run"} <= set(res["metadata"])
    assert names == [*res["metadata"], "hil.recovered"]  # the copied ones, then provenance
    info = hil("info", out, "--json")
    assert info.returncode == 0, info.stderr
    assert json.loads(info.stdout)["truncated"] is False
    assert json.loads(info.stdout)["ticks"] == res["cycles"]


def record_ends(data: bytes) -> list[int]:
    """File offsets where a top-level record of the data section ends."""
    from io import BytesIO

    fh = BytesIO(data)
    ends = []
    for rec in StreamReader(fh, emit_chunks=True).records:
        if type(rec).__name__ == "DataEnd":
            break
        ends.append(fh.tell())
    return ends


def test_a_log_cut_at_a_record_boundary_loses_nothing_it_holds(rig_log, tmp_path):
    data = rig_log.read_bytes()
    end = record_ends(data)[len(record_ends(data)) // 2]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:end])
    res = recover(cut, tmp_path / "recovered.mcap")
    assert res["lost_bytes"] == 0 and res["kept_bytes"] == end
    assert res["stopped"] == "end of file"
    got = stock_messages(tmp_path / "recovered.mcap")
    assert by_time(got) == by_time(stream_messages(data, upto=end)) and got


def test_a_finished_log_is_copied_whole(rig_log, tmp_path):
    res = recover(rig_log, tmp_path / "copy.mcap")
    assert res["finished"] and res["lost_bytes"] == 0
    assert by_time(stock_messages(tmp_path / "copy.mcap")) == by_time(stock_messages(rig_log))


RECORDER = """
import os, sys, time
import can
from hal.config import RigConfig
from rt_controller.runtime.recorder import CycleRecorder

rec = CycleRecorder(sys.argv[1], RigConfig(), run_info={"clock": "realtime"}, chunk_size=2048)
for k in range(3000):
    rec.record_can(can.Message(arbitration_id=0x10, data=k.to_bytes(4, "little")), k * 1000, "rx")
    if k % 100 == 99:
        rec.flush()
print("ready", flush=True)
for k in range(3000, 3050):  # written into the open chunk, never flushed: lost with the process
    rec.record_can(can.Message(arbitration_id=0x10, data=k.to_bytes(4, "little")), k * 1000, "rx")
time.sleep(60)
"""


def test_a_recorder_killed_with_sigkill(tmp_path):
    log = tmp_path / "killed.mcap"
    child = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(RECORDER), str(log)],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert child.stdout.readline().strip() == "ready"
    finally:
        os.kill(child.pid, signal.SIGKILL)
        child.wait()
    with pytest.raises((McapError, ValueError, EOFError)), log.open("rb") as fh:
        make_reader(fh).get_summary()
    done = hil("recover", log)
    assert done.returncode == 0, done.stderr
    out = tmp_path / "killed.recovered.mcap"  # the default name, beside the log
    assert done.stdout.startswith(f"{out}: kept 3000 message(s)")
    frames = [m for m in stock_messages(out) if m[0] == "/hal/can/rx"]
    assert [json.loads(m[2])["data"] for m in frames] == [
        k.to_bytes(4, "little").hex() for k in range(3000)
    ]


def test_attachments_and_metadata_survive(tmp_path):
    log = tmp_path / "other.mcap"
    with log.open("wb") as fh:
        w = Writer(fh)
        w.start(profile="x", library="other-tool")
        w.add_attachment(1, 2, "calib.yaml", "text/yaml", b"k: 1\n")
        w.add_metadata("site", {"lab": "A"})
        sid = w.register_schema("s", "jsonschema", b"{}")
        cid = w.register_channel("/a", "json", sid)
        for k in range(50):
            w.add_message(cid, k, b"{}", k)
        w.finish()
    cut = tmp_path / "cut.mcap"
    data = log.read_bytes()
    cut.write_bytes(data[: record_ends(data)[-1]])  # no DataEnd, summary or footer
    res = recover(cut, tmp_path / "r.mcap")
    with (tmp_path / "r.mcap").open("rb") as fh:
        reader = make_reader(fh)
        assert [(a.name, a.data) for a in reader.iter_attachments()] == [("calib.yaml", b"k: 1\n")]
        meta = [(m.name, m.metadata) for m in reader.iter_metadata()]
        assert meta[0] == ("site", {"lab": "A"}) and meta[1][0] == "hil.recovered"
        assert meta[1][1]["from"] == str(cut) and meta[1][1]["stopped"] == "end of file"
        assert reader.get_header().library == "other-tool"
    assert res["attachments"] == 1 and res["messages"] == 50


def test_refuses_to_overwrite_its_input(rig_log, tmp_path):
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(rig_log.read_bytes()[:50_000])
    before = cut.read_bytes()
    for out in (cut, tmp_path / "." / "cut.mcap"):
        done = hil("recover", cut, "--out", out)
        assert done.returncode == 2 and "never overwrites" in done.stderr
        assert len(done.stderr.strip().splitlines()) == 1
    assert cut.read_bytes() == before


def test_random_bytes_are_one_line_and_exit_2(tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(os.urandom(4096))
    done = hil("recover", junk)
    assert done.returncode == 2
    assert done.stderr.strip() == f"hil recover: error: {junk}: not an MCAP file (bad magic)"
    assert not (tmp_path / "junk.recovered.mcap").exists()
    headless = tmp_path / "headless.mcap"
    headless.write_bytes(b"\x89MCAP0\r\n\x01\x05")
    done = hil("recover", headless)
    assert done.returncode == 2 and "nothing to recover" in done.stderr, done.stderr
    assert sorted(tmp_path.iterdir()) == sorted([junk, headless])  # no copy, no partial file
