"""Fixtures of the emulator tests: ``can_spec``, the CAN transports the emulator process tests
run on (``tests/support/emulator_proc.py``)."""

from __future__ import annotations

import pytest

from hal.bus import isolated_spec
from tests.support.emulator_proc import TRANSPORTS
from tests.support.vcan import VCAN_CHANNEL


@pytest.fixture(params=TRANSPORTS)
def can_spec(request: pytest.FixtureRequest) -> str:
    """Each transport of ``TRANSPORTS`` (its marks go with it): vcan0, or an isolated
    ``udp_multicast`` port."""
    if request.param == "socketcan":
        return f"socketcan:{VCAN_CHANNEL}"
    return isolated_spec(request.param)
