"""A process that hangs while stopping says where: every thread's stack on stderr; an orphan
(its parent died first, as a SIGKILLed ``hil up``'s children) then exits by itself."""

import os
import signal
import subprocess
import sys
import textwrap

import pytest

CHILD = textwrap.dedent(
    """
    import sys, time
    import hal.signals as s
    s.STACKS_AFTER_S = 0.2
    def hang_while_stopping():
        time.sleep(10)  # far longer than the dump's delay, on any scheduling
    with s.stop_on_signals() as stop:
        print("ready", flush=True)
        stop.wait()
        if sys.argv[1] == "hang":
            hang_while_stopping()
        elif sys.argv[1] == "forever":
            time.sleep(600)  # a stop that never ends
    """
)
GIL_HELD = textwrap.dedent(
    """
    import ctypes, threading, time
    import hal.signals as s
    def hold_the_gil():
        ctypes.PyDLL(None).sleep(600)  # blocked in C with the GIL: no Python handler runs
    with s.stop_on_signals() as stop:
        print("ready", flush=True)
        threading.Thread(target=hold_the_gil, daemon=True).start()
        stop.wait()
    """
)


MIDDLE = (
    "import subprocess, sys; p = subprocess.Popen(sys.argv[1:], stdout=subprocess.PIPE, "
    "text=True); assert p.stdout.readline() == 'ready\\n'; print(p.pid, flush=True)"
)
ORPHANAGE = textwrap.dedent(
    """
    import ctypes, os, signal, subprocess, sys
    CHILD, MIDDLE = sys.argv[1:3]
    ctypes.CDLL(None).prctl(36, 1, 0, 0, 0)  # PR_SET_CHILD_SUBREAPER: orphans come here
    middle = subprocess.Popen(  # starts the child, and exits once the child is ready
        [sys.executable, "-c", MIDDLE, sys.executable, "-c", CHILD, "forever"],
        stdout=subprocess.PIPE, text=True,
    )
    pid = int(middle.stdout.readline())
    middle.wait()  # the child's parent is gone: it is an orphan, now ours
    os.kill(pid, signal.SIGTERM)  # as the parent-death signal would
    _, status = os.waitpid(pid, 0)
    print("exit", os.waitstatus_to_exitcode(status), flush=True)
    """
)


def _ready(script: str, *args: str) -> subprocess.Popen:
    """A child running ``script``, once it said it is ready (its handlers are in)."""
    proc = subprocess.Popen(
        [sys.executable, "-c", script, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout.readline() == "ready\n"
    return proc


def _stop(mode: str) -> str:
    """Start the child, SIGTERM it once ready, and return its stderr once it has exited."""
    proc = _ready(CHILD, mode)
    try:
        proc.send_signal(signal.SIGTERM)
        return proc.communicate(timeout=60)[1]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_a_stop_that_hangs_prints_every_threads_stack():
    err = _stop("hang")
    assert "most recent call first" in err and "hang_while_stopping" in err


def test_a_prompt_stop_prints_nothing():
    assert "most recent call first" not in _stop("quick")


def test_an_orphan_whose_stop_hangs_exits_after_the_dump():
    proc = subprocess.Popen(
        [sys.executable, "-c", ORPHANAGE, CHILD, MIDDLE],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:  # the orphan hung: take it and its keeper down
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert "exit 1" in out, (out, err)
    assert "most recent call first" in err, err


def test_a_child_hung_with_the_gil_held_is_killed_with_its_stacks():
    """The stop signal's Python handler never runs (another thread holds the GIL in C), so
    no timed dump either: the supervisor's stack signal still names where it hangs."""
    from rt_controller.rig.supervise import kill_with_stacks

    proc = _ready(GIL_HELD)
    try:
        proc.send_signal(signal.SIGTERM)
        with pytest.raises(subprocess.TimeoutExpired):
            proc.wait(1.0)  # the stop hangs
        kill_with_stacks(proc)
        err = proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert "most recent call first" in err and "hold_the_gil" in err, err
