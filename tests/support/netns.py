"""Two Linux network namespaces joined by a veth pair, for tests of the rig across hosts.

The addresses are :data:`ADDRS` (192.0.2.0/24, TEST-NET-1), inside the namespaces only. Needs
root and ``ip netns``; the test skips with one line where the namespaces cannot be made.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
from collections.abc import Iterator

import pytest

ADDRS = ("192.0.2.1", "192.0.2.2")
"""The first namespace's address, the second's."""


def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=False)


@contextlib.contextmanager
def veth_namespaces(first: str, second: str, link: str) -> Iterator[tuple[str, str]]:
    """The namespaces ``first`` and ``second`` (this process's id appended) with the veth pair
    ``link``-a / ``link``-b between them, loopback up; both are deleted afterwards."""
    tag = f"{os.getpid() % 100000}"
    a, b = f"{first}{tag}", f"{second}{tag}"
    la, lb = f"{link}{tag}a", f"{link}{tag}b"
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root")
    made = _ip("netns", "add", a)
    if made.returncode != 0:
        pytest.skip(f"cannot make a network namespace: {made.stderr.strip()}")
    try:
        steps = [
            ("netns", "add", b),
            ("link", "add", la, "type", "veth", "peer", "name", lb),
            ("link", "set", la, "netns", a),
            ("link", "set", lb, "netns", b),
            ("-n", a, "addr", "add", f"{ADDRS[0]}/24", "dev", la),
            ("-n", b, "addr", "add", f"{ADDRS[1]}/24", "dev", lb),
            ("-n", a, "link", "set", la, "up"),
            ("-n", b, "link", "set", lb, "up"),
            ("-n", a, "link", "set", "lo", "up"),
            ("-n", b, "link", "set", "lo", "up"),
        ]
        for step in steps:
            done = _ip(*step)
            if done.returncode != 0:
                pytest.skip(f"cannot set up the namespaces ({' '.join(step)}): {done.stderr}")
        yield a, b
    finally:
        _ip("netns", "del", b)
        _ip("netns", "del", a)
