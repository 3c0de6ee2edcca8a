#!/usr/bin/env python3
"""Peer check: python-can's own back-to-back suite, run unmodified against hal.udp_loopback.

Takes ``test/back2back_test.py`` (and the modules of its ``test`` package it imports, e.g.
``config.py``) from the source distribution of the *installed* python-can version, downloaded by
pip into a cache (nothing of it is copied into this repository), and runs it with pytest against
:class:`hal.udp_loopback.LoopbackMulticastBus`, registered as the python-can interface
``hal_udp_multicast`` through python-can's plugin mechanism (a ``can.interface`` entry point in a
throw-away ``.dist-info`` on the child's ``sys.path``).

The suite's own test classes are reused by subclassing, with only the interface and channel
changed: ``Back2BackTestCase`` (basic) and ``TestThreadSafeBus`` (thread-safe), each for an IPv4
group and for python-can's host-local IPv6 group. A group the bus refuses at open
(:class:`~hal.udp_loopback.GroupUnreachableError`, e.g. IPv6 where ``lo`` has no multicast route)
is skipped with the bus's one-line reason; any failure or error fails the check. The port is
reserved for this process with :func:`hal.bus.isolated_spec`, so parallel runs never cross-talk.

Flaky-test policy: upstream's suite has wall-clock assertions of its own (e.g.
``test_send_periodic_duration`` needs python-can's periodic thread to start within 10 ms), which
a loaded machine can miss. Tests that fail (or error) in the first run are therefore run once
more, alone, in a fresh pytest process; a test that passes on that rerun counts as passed and is
named in the summary line (``flaky: passed on rerun: ...``), a test that fails twice fails the
check. Nothing else is retried, and a rerun never hides a failure that repeats.

Prints one summary line; exit status 0 = passed, 1 = a test failed (twice), 2 = the suite could
not be obtained or run.

    python scripts/can_peer_suite.py [--cache DIR] [-v] [--keep]
"""

from __future__ import annotations

import argparse
import ast
import importlib.metadata
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import xml.etree.ElementTree as ET
from collections import Counter
from pathlib import Path, PurePosixPath

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hal.bus import isolated_spec, parse_spec  # noqa: E402

INTERFACE = "hal_udp_multicast"
SUITE = "back2back_test.py"

WRAPPER = '''"""Generated: python-can's back2back_test, imported unmodified, on hal.udp_loopback."""

import os
import unittest

import can

from hal.udp_loopback import GroupUnreachableError
from test import back2back_test as upstream

INTERFACE = "{interface}"
IPV4_GROUP = os.environ.get("HAL_PEER_IPV4_GROUP", upstream.UdpMulticastBus.DEFAULT_GROUP_IPv4)
IPV6_GROUP = upstream.BasicTestUdpMulticastBusIPv6.HOST_LOCAL_MCAST_GROUP_IPv6


def _refused(group):
    """The bus's one-line reason when it refuses ``group`` at open, else None."""
    try:
        bus = can.Bus(interface=INTERFACE, channel=group)
    except GroupUnreachableError as exc:
        return str(exc)
    bus.shutdown()
    return None


def _skip_if_refused(group):
    reason = _refused(group)
    return unittest.skip(f"refused at open: {{reason}}") if reason else (lambda cls: cls)


@_skip_if_refused(IPV4_GROUP)
class TestHalIPv4(upstream.Back2BackTestCase):
    INTERFACE_1 = INTERFACE_2 = INTERFACE
    CHANNEL_1 = CHANNEL_2 = IPV4_GROUP


@_skip_if_refused(IPV4_GROUP)
class TestHalIPv4ThreadSafe(upstream.TestThreadSafeBus):
    INTERFACE_1 = INTERFACE_2 = INTERFACE
    CHANNEL_1 = CHANNEL_2 = IPV4_GROUP


@_skip_if_refused(IPV6_GROUP)
class TestHalIPv6(upstream.Back2BackTestCase):
    INTERFACE_1 = INTERFACE_2 = INTERFACE
    CHANNEL_1 = CHANNEL_2 = IPV6_GROUP


@_skip_if_refused(IPV6_GROUP)
class TestHalIPv6ThreadSafe(upstream.TestThreadSafeBus):
    INTERFACE_1 = INTERFACE_2 = INTERFACE
    CHANNEL_1 = CHANNEL_2 = IPV6_GROUP
'''


class PeerSuiteError(Exception):
    """The suite could not be obtained or run (exit status 2)."""


def default_cache() -> Path:
    env = os.environ.get("HIL_PEER_CACHE")
    if env:
        return Path(env)
    venv = Path(sys.prefix)
    if sys.prefix != sys.base_prefix and os.access(venv, os.W_OK):
        return venv / "cache" / "python-can-sdist"
    return Path(tempfile.gettempdir()) / "hil-python-can-sdist"


def fetch_sdist(version: str, cache: Path) -> Path:
    """The cached sdist of python-can ``version``, downloaded by pip if missing."""
    cache.mkdir(parents=True, exist_ok=True)
    found = sorted(cache.glob(f"python[-_]can-{version}.tar.gz"))
    if found:
        return found[0]
    cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--no-binary"]
    cmd += [":all:", f"python-can=={version}", "--dest", str(cache)]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    found = sorted(cache.glob(f"python[-_]can-{version}.tar.gz"))
    if proc.returncode != 0 or not found:
        last = (proc.stderr.strip().splitlines() or ["no sdist in the download"])[-1]
        raise PeerSuiteError(f"pip download python-can=={version} (sdist) failed: {last}")
    return found[0]


def _relative_imports(source: str) -> set[str]:
    """Module names imported relative to the package (``from .config import X``)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            if node.module:
                names.add(node.module.split(".")[0])
            else:
                names.update(alias.name for alias in node.names)
    return names


def extract_suite(sdist: Path, dest: Path) -> list[str]:
    """Extract ``test/back2back_test.py`` and the ``test`` modules it needs, byte for byte."""
    pkg = dest / "test"
    pkg.mkdir(parents=True)
    with tarfile.open(sdist) as tar:
        members = {}
        for member in tar.getmembers():
            parts = PurePosixPath(member.name).parts
            if member.isfile() and len(parts) == 3 and parts[1] == "test":
                members[parts[2]] = member
        if SUITE not in members:
            raise PeerSuiteError(f"{sdist.name} has no test/{SUITE}")
        wanted, done = ["__init__.py", SUITE], []
        while wanted:
            name = wanted.pop()
            if name in done or name not in members:
                continue
            fh = tar.extractfile(members[name])
            if fh is None:  # pragma: no cover - a regular file always has content
                raise PeerSuiteError(f"cannot read test/{name} from {sdist.name}")
            data = fh.read()
            (pkg / name).write_bytes(data)
            done.append(name)
            wanted += [f"{mod}.py" for mod in _relative_imports(data.decode("utf-8"))]
    return sorted(done)


def register_plugin(dest: Path) -> None:
    """python-can's plugin mechanism: a ``can.interface`` entry point naming the HAL bus."""
    info = dest / "hal_can_peer-0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: hal-can-peer\nVersion: 0\n")
    (info / "entry_points.txt").write_text(
        f"[can.interface]\n{INTERFACE} = hal.udp_loopback:LoopbackMulticastBus\n"
    )


def failed_tests(junit: Path) -> dict[str, str]:
    """Node id (``test_hal_peer.py::Class::test``) -> ``failed`` or ``error``, of every test
    that did not pass."""
    out = {}
    for case in ET.parse(junit).iter("testcase"):
        kinds = [child.tag for child in case if child.tag in ("failure", "error")]
        if kinds:
            cls = case.get("classname", "").rsplit(".", 1)[-1]
            kind = "failed" if kinds[0] == "failure" else "error"
            out[f"test_hal_peer.py::{cls}::{case.get('name', '')}"] = kind
    return out


def summarise(junit: Path) -> dict[str, Counter[str]]:
    """Outcome counts per address family from pytest's JUnit XML."""
    out: dict[str, Counter[str]] = {"IPv4": Counter(), "IPv6": Counter()}
    skip_reasons: dict[str, str] = {}
    for case in ET.parse(junit).iter("testcase"):
        family = "IPv6" if "IPv6" in case.get("classname", "") else "IPv4"
        kinds = [child.tag for child in case if child.tag in ("failure", "error", "skipped")]
        outcome = {"failure": "failed", "error": "error", "skipped": "skipped"}.get(
            kinds[0] if kinds else "", "passed"
        )
        out[family][outcome] += 1
        if outcome == "skipped":
            message = case.find("skipped").get("message", "")  # type: ignore[union-attr]
            if "refused at open" in message:
                skip_reasons[family] = message.split("refused at open: ", 1)[-1]
    for family, reason in skip_reasons.items():
        out[family]["refused"] = 1
        out[family + " reason"] = Counter({reason: 1})
    return out


def run(cache: Path, verbose: bool, keep: bool) -> tuple[int, str]:
    version = importlib.metadata.version("python-can")
    sdist = fetch_sdist(version, cache)
    spec = parse_spec(isolated_spec("udp_multicast"))  # reserved for this process's lifetime
    work = Path(tempfile.mkdtemp(prefix="hil-can-peer-"))
    try:
        modules = extract_suite(sdist, work)
        register_plugin(work)
        (work / "test_hal_peer.py").write_text(WRAPPER.format(interface=INTERFACE))
        (work / "pytest.ini").write_text("[pytest]\naddopts = -rfE -p no:cacheprovider\n")
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(
            [str(work), str(ROOT), *filter(None, [env.get("PYTHONPATH")])]
        )
        env["CAN_CONFIG"] = json.dumps({"port": spec.kwargs["port"]})
        env["HAL_PEER_IPV4_GROUP"] = str(spec.channel)
        for var in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE"):
            env.pop(var, None)

        def pytest_run(junit: Path, targets: list[str]) -> subprocess.CompletedProcess[str]:
            cmd = [sys.executable, "-m", "pytest", "-c", str(work / "pytest.ini")]
            cmd += ["--rootdir", str(work), "--junitxml", str(junit), "-o", "timeout=120"]
            cmd += ["-q", *targets]
            proc = subprocess.run(cmd, cwd=work, env=env, capture_output=not verbose, text=True)
            if not junit.exists():
                tail = (proc.stdout or "").strip().splitlines()[-5:] if not verbose else []
                raise PeerSuiteError(
                    f"pytest did not run the suite (exit {proc.returncode}): {tail}"
                )
            return proc

        junit = work / "junit.xml"
        proc = pytest_run(junit, [str(work / "test_hal_peer.py")])
        counts = summarise(junit)
        flaky: list[str] = []
        first_failed = failed_tests(junit)
        if first_failed:  # the flaky-test policy: each failed test once more, alone
            rerun_junit = work / "junit-rerun.xml"
            rerun = pytest_run(rerun_junit, list(first_failed))
            still = failed_tests(rerun_junit)
            flaky = [t for t in first_failed if t not in still]
            for test in flaky:
                family = "IPv6" if "IPv6" in test else "IPv4"
                counts[family][first_failed[test]] -= 1
                counts[family]["passed"] += 1
            if flaky and not verbose:  # the first failure stays visible
                sys.stderr.write(proc.stdout[-3000:])
            if not still and rerun.returncode == 0:
                proc = rerun  # every failure of the first run passed on its rerun
        parts = []
        for family in ("IPv4", "IPv6"):
            c = counts[family]
            if c["refused"] and not (c["passed"] or c["failed"] or c["error"]):
                reason = next(iter(counts[family + " reason"]))
                parts.append(f"{family} skipped, {c['skipped']} tests (refused at open: {reason})")
            else:
                parts.append(
                    f"{family} {c['passed']} passed, {c['failed']} failed, "
                    f"{c['error']} errors, {c['skipped']} skipped"
                )
        bad = sum(counts[f]["failed"] + counts[f]["error"] for f in ("IPv4", "IPv6"))
        passed = sum(counts[f]["passed"] for f in ("IPv4", "IPv6"))
        ok = proc.returncode == 0 and bad == 0 and passed > 0
        if not ok and bad == 0:
            bad = 1
        if not ok and not verbose:
            sys.stderr.write(proc.stdout[-6000:])
        head = f"python-can {version} test/{SUITE} ({', '.join(modules)}) vs hal.udp_loopback"
        verdict = "OK" if ok else "FAILED"
        if flaky:
            names = ", ".join(t.split("::", 1)[1] for t in flaky)
            verdict += f" (flaky: passed on rerun: {names})"
        return (0 if ok else 1), f"{head}: {'; '.join(parts)}: {verdict}"
    finally:
        if keep:
            print(f"kept {work}", file=sys.stderr)
        else:
            subprocess.run(["rm", "-rf", str(work)], check=False)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--cache",
        type=Path,
        default=None,
        help="directory caching python-can's sdist (default: $HIL_PEER_CACHE, else "
        ".venv/cache/python-can-sdist if writable, else a temporary folder)",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="show pytest's output")
    parser.add_argument("--keep", action="store_true", help="keep the generated suite directory")
    args = parser.parse_args(argv)
    try:
        status, line = run(args.cache or default_cache(), args.verbose, args.keep)
    except (PeerSuiteError, OSError, tarfile.TarError, ET.ParseError) as exc:
        print(f"python-can peer suite: cannot run: {exc}")
        return 2
    print(line)
    return status


if __name__ == "__main__":
    sys.exit(main())
