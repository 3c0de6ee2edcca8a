"""``transport.zenoh_endpoint`` is checked with the configuration: a run given one that is not
loopback is refused in one line before its recorder starts, and leaves no log."""

from __future__ import annotations

import pytest

from hal.bus import isolated_spec
from hal.config import load_config
from hal.errors import HalConfigError
from tests.support import run_hil

BAD = "tcp/10.0.0.1:7447"


def test_the_configuration_refuses_an_endpoint_off_the_host(tmp_path):
    path = tmp_path / "rig.toml"
    path.write_text(f'[transport]\nzenoh_endpoint = "{BAD}"\n', encoding="utf-8")
    with pytest.raises(HalConfigError, match=r"transport\.zenoh_endpoint: .*not an IPv4 loopback"):
        load_config(path)
    cfg = load_config().with_overrides({"transport.zenoh_config": "rig.json5"})
    assert cfg.with_overrides({"transport.zenoh_endpoint": BAD}).transport.zenoh_endpoint == BAD
    assert load_config().with_overrides({"transport.zenoh_endpoint": ""})  # the default one


@pytest.mark.parametrize("where", ["option", "config"])
def test_a_run_with_a_bad_endpoint_is_refused_before_anything_starts(tmp_path, where):
    key, log, config = tmp_path / "rig.key", tmp_path / "run.mcap", tmp_path / "rig.toml"
    assert run_hil(["keygen", str(key)], timeout_s=60).returncode == 0
    config.write_text('[transport]\nzenoh_endpoint = "foo"\n', encoding="utf-8")
    source = ["--zenoh-endpoint", "foo"] if where == "option" else ["--config", str(config)]
    argv = ["controller", "--key-file", str(key), "--log", str(log), "--duration", "1"]
    out = run_hil([*argv, *source, "--can", isolated_spec("udp_multicast")], timeout_s=120)
    assert out.returncode == 2, out.stderr
    assert out.stderr.startswith("hil controller: error: ")
    assert "transport.zenoh_endpoint" in out.stderr and "'foo'" in out.stderr
    assert "Traceback" not in out.stderr and len(out.stderr.strip().splitlines()) == 1
    assert not log.exists()


@pytest.mark.parametrize("kind", ["folder", "fifo", "not-utf8", "bad-json5"])
def test_a_zenoh_config_file_zenoh_cannot_read_is_refused_in_one_line(tmp_path, kind):
    """Before its recorder starts (no warning of a live stream first), naming the file and
    what is wrong with it: never a hang on a FIFO, "no such file" for a folder, or zenoh's
    Rust source locations."""
    import os

    key, log, zcfg = tmp_path / "rig.key", tmp_path / "run.mcap", tmp_path / "zenoh.json5"
    if kind == "folder":
        zcfg.mkdir()
    elif kind == "fifo":
        os.mkfifo(zcfg)
    elif kind == "not-utf8":
        zcfg.write_bytes(b"\xff\xfe{ mode: 'peer' }")
    else:  # zenoh's parser draws its error over several lines
        zcfg.write_text('{ mode: "client", connect: { endpoints: [] , }\n  listen: [[ }')
    assert run_hil(["keygen", str(key)], timeout_s=60).returncode == 0
    argv = ["controller", "--key-file", str(key), "--log", str(log), "--duration", "1"]
    argv += ["--zenoh-config", str(zcfg), "--can", isolated_spec("udp_multicast")]
    out = run_hil(argv, timeout_s=120)
    assert out.returncode == 2, out.stderr
    (line,) = out.stderr.strip().splitlines()
    assert line.startswith("hil controller: error: ") and str(zcfg) in line
    said = {"folder": "is a directory", "fifo": "not a regular file", "not-utf8": "not UTF-8"}
    said["bad-json5"] = "line 1, column 46: expected identifier or string"
    assert said[kind] in line and ".rs:" not in line
    assert not log.exists()
