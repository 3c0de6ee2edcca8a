"""Helpers for tests that need a real SocketCAN ``vcan0`` (pytest marker ``vcan``).

Usage in a test module::

    import pytest
    from tests.support.vcan import VCAN_CHANNEL, requires_vcan

    pytestmark = [pytest.mark.vcan, requires_vcan]

``requires_vcan`` skips when the interface is missing, unless ``HIL_VCAN_REQUIRED=1`` is set
(``scripts/vcan_pytest.py`` sets it after creating vcan0, natively or inside user-mode Linux):
then the tests run and fail loudly rather than skip silently.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from hal.bus import vcan_available

VCAN_CHANNEL = os.environ.get("HIL_VCAN_CHANNEL", "vcan0")
ENABLE_HINT = (
    "run `scripts/vcan_pytest.py` (boots user-mode Linux if needed) or create it: "
    "sudo modprobe vcan; sudo ip link add dev vcan0 type vcan; sudo ip link set vcan0 mtu 72; "
    "sudo ip link set up vcan0"
)
LOCKSTEP_REPLY_TIMEOUT_S = 10.0
"""``dsp.lockstep_reply_timeout_s`` for lockstep runs in the vcan tests: user-mode Linux runs the
rig about 10x slower than the host, and a period's command now and then missed the default 0.5 s
there (one held period makes a lockstep run not clean)."""
LOCKSTEP_REPLY_TOML = f"[dsp]\nlockstep_reply_timeout_s = {LOCKSTEP_REPLY_TIMEOUT_S}\n"
"""The same, as a rig configuration file's section."""


def vcan_required() -> bool:
    """True when a missing vcan interface must fail the tests instead of skipping them."""
    return os.environ.get("HIL_VCAN_REQUIRED", "").strip().lower() in {"1", "true", "yes"}


def vcan_skip_reason(channel: str = VCAN_CHANNEL) -> str:
    if not (Path("/sys/class/net") / channel).exists():
        return f"no SocketCAN interface {channel}; {ENABLE_HINT}"
    return f"SocketCAN interface {channel} is down; sudo ip link set up {channel}"


def candump_available() -> bool:
    return shutil.which("candump") is not None


requires_vcan = pytest.mark.skipif(
    not vcan_available(VCAN_CHANNEL) and not vcan_required(), reason=vcan_skip_reason()
)
requires_candump = pytest.mark.skipif(
    not candump_available() and not vcan_required(),
    reason="candump not found (sudo apt-get install can-utils)",
)
