"""The rig across hosts, the way a lab deploys it: the real-time host (emulator/DSP and
controller, CAN on its own loopback) and the camera host (vision) are two Linux network
namespaces joined by a veth pair (192.0.2.0/24, TEST-NET-1, inside the namespaces only), zenoh
over TCP and over mutually authenticated TLS with certificates made by the openssl commands of
docs/tutorials/two-hosts.md. Every process loads the same rig key. The run must converge
(|f| < 1 px) as on one host.

Needs root and ``ip netns``; skips with one line where namespaces cannot be made.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from hal.bus import isolated_spec
from hal.secoc import write_key_file
from tests.support.netns import ADDRS, veth_namespaces

pytestmark = pytest.mark.integration

RT_ADDR, CAM_ADDR = ADDRS
WAIT_S = 120.0


@pytest.fixture
def namespaces() -> Iterator[tuple[str, str]]:
    with veth_namespaces("hilrt", "hilcam", "hv") as pair:
        yield pair


def make_certificates(out: Path) -> None:
    """CA, a hub certificate for RT_ADDR and a client certificate (the commands of
    docs/tutorials/two-hosts.md)."""
    sh = f"""set -e
cd {out}
openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -days 365 \\
  -keyout ca.key -out ca.pem -subj /CN=hil-rig-ca
for name in hub client; do
  openssl req -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes \\
    -keyout $name.key -out $name.csr -subj /CN=hil-$name
  printf 'subjectAltName=IP:{RT_ADDR}\\nbasicConstraints=CA:FALSE\\n' > $name.ext
  printf 'extendedKeyUsage=serverAuth,clientAuth\\n' >> $name.ext
  openssl x509 -req -in $name.csr -CA ca.pem -CAkey ca.key -CAcreateserial -days 365 \\
    -extfile $name.ext -out $name.pem
done
chmod 600 *.key
"""
    done = subprocess.run(["sh", "-c", sh], capture_output=True, text=True, check=False)
    if done.returncode != 0:
        pytest.skip(f"openssl cannot make certificates: {done.stderr.strip()[-200:]}")


def zenoh_configs(out: Path, proto: str, port: int) -> dict[str, Path]:
    """The json5 files of docs/tutorials/two-hosts.md: the emulator is the router (hub)."""
    common = {"scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}}
    tls = {}
    if proto == "tls":
        tls = {"root_ca_certificate": str(out / "ca.pem"), "enable_mtls": True}
    endpoint = f"{proto}/{RT_ADDR}:{port}"

    def link(name: str, listen: bool) -> dict:
        if not tls:
            return {}
        own = {
            "connect_private_key": str(out / f"{name}.key"),
            "connect_certificate": str(out / f"{name}.pem"),
        }
        if listen:
            own |= {
                "listen_private_key": str(out / f"{name}.key"),
                "listen_certificate": str(out / f"{name}.pem"),
            }
        return {"transport": {"link": {"tls": {**tls, **own}}}}

    docs = {
        "hub": {
            "mode": "router",
            "listen": {"endpoints": [endpoint]},
            **common,
            **link("hub", True),
        },
        "client": {
            "mode": "client",
            "connect": {"endpoints": [endpoint]},
            **common,
            **link("client", False),
        },
    }
    paths = {}
    for name, doc in docs.items():
        paths[name] = out / f"{proto}-{name}.json5"
        paths[name].write_text(json.dumps(doc, indent=2))
    return paths


def _start(ns: str, args: list[str], out: Path, name: str) -> subprocess.Popen:
    cmd = ["ip", "netns", "exec", ns, sys.executable, "-m", "rt_controller.cli", *args]
    return subprocess.Popen(
        cmd,
        stdout=(out / f"{name}.out").open("wb"),
        stderr=(out / f"{name}.err").open("wb"),
        stdin=subprocess.DEVNULL,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def _wait_line(path: Path, text: str, proc: subprocess.Popen) -> None:
    deadline = time.monotonic() + WAIT_S
    while text not in path.read_text(errors="replace"):
        if proc.poll() is not None or time.monotonic() > deadline:
            pytest.fail(f"no {text!r} in {path.name}:\n{path.read_text(errors='replace')}")
        time.sleep(0.05)


@pytest.mark.parametrize("proto", ["tcp", "tls"])
def test_vision_on_another_host_over_zenoh(namespaces, tmp_path: Path, proto: str) -> None:
    rt, cam = namespaces
    if proto == "tls":
        make_certificates(tmp_path)
    cfgs = zenoh_configs(tmp_path, proto, 17447)
    key = str(write_key_file(tmp_path / "rig.key"))
    can = isolated_spec("udp_multicast")  # the real-time host's own loopback
    common = ["--key-file", key]
    procs: list[subprocess.Popen] = []
    try:
        emu = _start(
            rt,
            ["emulator", "--lockstep", "--can", can, "--zenoh-config", str(cfgs["hub"]), *common],
            tmp_path,
            "emulator",
        )
        procs.append(emu)
        _wait_line(tmp_path / "emulator.err", "serving", emu)
        procs.append(
            _start(
                cam, ["vision", "--zenoh-config", str(cfgs["client"]), *common], tmp_path, "vision"
            )
        )
        ctl = _start(
            rt,
            [
                "controller",
                "--clock",
                "lockstep",
                "--can",
                can,
                "--law",
                "ioc",
                "--duration",
                "10",
                "--json",
                "--log",
                str(tmp_path / "run.mcap"),
                "--zenoh-config",
                str(cfgs["client"]),
                *common,
            ],
            tmp_path,
            "controller",
        )
        procs.append(ctl)
        ctl.wait(WAIT_S)
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
    err = (tmp_path / "controller.err").read_text(errors="replace")
    lines = [ln for ln in (tmp_path / "controller.out").read_text().splitlines() if ln[:1] == "{"]
    assert lines, err
    summary = json.loads(lines[-1])
    print(
        f"NETNS {proto} | |f| {summary['f_final_norm']:.3f} px | J {summary['J']:.2f} | "
        f"features accepted {summary['rejections']['features'].get('accepted')} | "
        f"exit {ctl.returncode}"
    )
    assert ctl.returncode == 0, err
    assert summary["f_final_norm"] < 1.0, summary["f_final_norm"]
    assert summary["rejections"]["features"]["rejected"] == 0
