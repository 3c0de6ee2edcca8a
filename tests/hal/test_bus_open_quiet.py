"""A SocketCAN interface that cannot be opened gives our one-line error only: python-can's own
"Could not access SocketCAN device ..." log line is not shown as well.

On a kernel without SocketCAN (AF_CAN) python-can fails before it logs; on one with SocketCAN
(user-mode Linux, where ``scripts/vcan_pytest.py`` runs the ``vcan`` tests) it logs that line
for a missing interface, which is what this checks."""

from __future__ import annotations

import logging

import pytest

from hal.bus import open_bus
from hal.errors import HalTransportError

MISSING = "socketcan:hilnope0"
"""An interface that cannot exist (not vcan0, not a real adapter)."""

pytestmark = pytest.mark.vcan  # run where SocketCAN exists (user-mode Linux): it can fail there


def test_a_missing_socketcan_interface_logs_nothing_from_python_can(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="can")
    with pytest.raises(HalTransportError, match="cannot open CAN interface socketcan:hilnope0"):
        open_bus(MISSING)
    said = [f"{r.name}: {r.getMessage()}" for r in caplog.records if r.levelno >= logging.INFO]
    assert said == [], said


def test_python_can_logging_after_a_failed_open_is_untouched(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="can")
    with pytest.raises(HalTransportError):
        open_bus(MISSING)
    logging.getLogger("can.interfaces.socketcan.socketcan").error("later")
    assert [r.getMessage() for r in caplog.records] == ["later"]
