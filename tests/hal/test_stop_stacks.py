"""A process that hangs while stopping says where: every thread's stack on stderr."""

import signal
import subprocess
import sys
import textwrap

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
    """
)


def _stop(mode: str) -> str:
    """Start the child, SIGTERM it once ready, and return its stderr once it has exited."""
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, mode],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout.readline() == "ready\n"
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
