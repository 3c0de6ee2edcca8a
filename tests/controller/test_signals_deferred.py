"""``signals_deferred`` holds SIGINT/SIGTERM until its block ends, also when other threads run.

A process-directed signal goes to any thread that does not block it, and CPython then runs the
Python handler in the main thread at its next bytecode: blocking the signal in the main thread
alone defers nothing once a library (Dask, zenoh) has started a thread.
"""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from rt_controller.rig.supervise import signals_deferred


@pytest.fixture(autouse=True)
def python_sigint_handler():
    """Python's own SIGINT handler, whatever this process inherited: a shell starts background
    jobs with SIGINT ignored, and Python then leaves it so."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


@pytest.fixture
def other_thread():
    stop = threading.Event()
    thread = threading.Thread(target=stop.wait, daemon=True)
    thread.start()
    yield thread
    stop.set()
    thread.join()


@pytest.mark.parametrize("threads", [False, True], ids=["main-only", "with-a-thread"])
def test_a_signal_inside_the_block_is_delivered_after_it(threads: bool, request):
    if threads:
        request.getfixturevalue("other_thread")
    steps: list[str] = []
    with pytest.raises(KeyboardInterrupt):
        with signals_deferred():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)  # the handler would run here, were the signal not held
            steps.append("block ended")
        steps.append("after the block")  # never reached: the held signal is raised at the exit
    assert steps == ["block ended"]


def test_nothing_is_raised_without_a_signal(other_thread):
    with signals_deferred():
        pass
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_the_handlers_in_force_are_restored(other_thread):
    seen: list[int] = []
    previous = signal.signal(signal.SIGTERM, lambda signum, _frame: seen.append(signum))
    try:
        with signals_deferred():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
            assert seen == []
        time.sleep(0.01)
        assert seen == [signal.SIGTERM]
    finally:
        signal.signal(signal.SIGTERM, previous)
