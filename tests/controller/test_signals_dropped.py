"""``signals_deferred(deliver=False)`` drops the stop signals held in its block: ``hil up``
already stopping on a first Ctrl-C must not be cut short by a second one (its summary lost)."""

from __future__ import annotations

import os
import signal
import time

import pytest

from rt_controller.rig.supervise import signals_deferred


@pytest.fixture(autouse=True)
def python_sigint_handler():
    """Python's own SIGINT handler, whatever this process inherited (a shell's background job
    starts with SIGINT ignored)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_a_signal_held_without_delivery_is_dropped():
    steps: list[str] = []
    with signals_deferred(deliver=False):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)  # the handler would run here, were the signal not held
        steps.append("block ended")
    steps.append("after the block")
    assert steps == ["block ended", "after the block"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_a_signal_after_the_block_is_delivered_again():
    with signals_deferred(deliver=False):
        pass
    with pytest.raises(KeyboardInterrupt):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
