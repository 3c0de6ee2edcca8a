"""The Dask cluster of ``hil sweep`` and ``hil experiment``: a local one on 127.0.0.1, or an
existing one (``--scheduler``), checked before it is used: its address speaks Dask within
:data:`CONNECT_S` (Dask's client waits forever for the handshake of a peer that accepts and
stays silent) and a worker joins within :data:`WORKER_WAIT_S`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from rt_controller.errors import ControllerConfigError

WORKER_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
"""Each worker is one thread; its BLAS too (the control law's matrices are tiny)."""
MAX_WORKERS = 256
WORKER_WAIT_S = 60.0
"""With ``--scheduler``: how long to wait for a first worker before giving up."""
CONNECT_S = 20.0
"""With ``--scheduler``: how long the connection and Dask's handshake may take."""


def machine_workers() -> int:
    """Worker processes of a default local cluster: the CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


@dataclass
class Cluster:
    """A Dask client and, for a local cluster, the cluster it owns."""

    client: Any
    local: Any = None

    @property
    def address(self) -> str:
        return str(self.client.scheduler.address)

    @property
    def workers(self) -> int:
        return len(self.client.scheduler_info().get("workers", {}))

    def close(self) -> None:
        with contextlib.suppress(Exception):  # a cluster already going down on Ctrl-C
            self.client.close(timeout=10)
        if self.local is not None:
            with contextlib.suppress(Exception):
                self.local.close(timeout=10)


@contextlib.contextmanager
def _workers_ignore_sigint() -> Iterator[None]:
    """Start the local workers with SIGINT ignored (a spawned interpreter keeps an ignored
    SIGINT): Ctrl-C at a terminal signals the whole process group, and the sweep itself stops
    its workers in order instead of each one dying with a traceback."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


class Unusable(ConnectionError):
    """The ``--scheduler`` address cannot be a Dask scheduler hil can use, said in words."""


def check_address(address: str) -> None:
    """:class:`Unusable` at once for an address Dask's client would retry for
    :data:`CONNECT_S` or fail on obscurely: a scheme other than tcp (TLS and UCX need a
    security or transport setup hil does not take), a port out of range, a host that does not
    resolve, or nothing listening there."""
    import socket

    from distributed.comm.addressing import parse_address, parse_host_port

    scheme, loc = parse_address(address)  # no scheme: tcp
    if scheme != "tcp":
        raise Unusable(f"only tcp:// schedulers are supported, not {scheme}://")
    host, port = parse_host_port(loc)  # ValueError: no port
    if not 0 < int(port) < 65536:
        raise Unusable(f"port {port} is out of range (1..65535)")
    try:
        with socket.create_connection((host, int(port)), timeout=CONNECT_S):
            pass
    except socket.gaierror as exc:
        raise Unusable(f"unknown host {host} ({exc.strerror})") from None
    except ConnectionRefusedError:
        raise Unusable(
            f"connection refused: nothing listens on {host}:{port} (start one: dask scheduler "
            f"--port {port})"
        ) from None


class NoHandshake(TimeoutError):
    """The address accepted the connection and said nothing Dask understands in time."""


class NotAScheduler(Unusable):
    """The address is a Dask server of another kind (a worker, a nanny)."""


def handshake(address: str, timeout_s: float) -> None:
    """Connect to ``address``, exchange Dask's handshake and ask the server what it is within
    ``timeout_s`` + 10 s, then hang up: Dask's own client bounds the connection, not the
    handshake, so a peer that accepts and stays silent would keep it waiting for ever, and a
    worker's address fails later with a message about the worker's internals. The loop runs
    in a thread of its own, so that a Ctrl-C reaches this (main) thread as it does elsewhere."""
    import asyncio

    from distributed.comm import connect

    failed: list[BaseException] = []

    async def shake() -> None:
        try:  # connect's own timeout (with its reason) first, then the handshake's
            comm = await asyncio.wait_for(connect(address, timeout=timeout_s), timeout_s + 10)
            try:
                await comm.write({"op": "identity", "reply": True})
                reply = await asyncio.wait_for(comm.read(), timeout_s)
                kind = reply.get("type") if isinstance(reply, dict) else None
            finally:
                await comm.close()
        except TimeoutError:
            raise NoHandshake(f"no Dask handshake within {timeout_s + 10:g} s") from None
        if kind != "Scheduler":
            what = (kind or "server").lower()
            raise NotAScheduler(
                f"a Dask {what}, not a scheduler (`dask scheduler` prints its address, port "
                "8786 by default)"
            )

    def run() -> None:
        try:
            asyncio.run(shake())
        except BaseException as exc:  # handed to the caller
            failed.append(exc)

    thread = threading.Thread(target=run, name="hil-dask-handshake", daemon=True)
    thread.start()
    thread.join()  # a signal's handler raises here
    if failed:
        raise failed[0]


def open_cluster(
    workers: int | None = None,
    scheduler: str | None = None,
    *,
    processes: bool = True,
    workers_option: str = "--workers",
    worker_env: dict[str, str] | None = None,
) -> Cluster:
    """Connect to ``scheduler``, else start a local cluster of ``workers`` workers of one
    thread each on 127.0.0.1: processes (with ``worker_env`` added to :data:`WORKER_ENV`), or
    with ``processes=False`` threads of this process (for tasks that only supervise processes
    of their own, such as a rig's). ``workers_option`` names the option that sizes the local
    cluster in errors."""
    from distributed import Client, LocalCluster

    from rt_controller.rig.supervise import RigInterrupted

    if scheduler is not None:
        if workers is not None:
            raise ControllerConfigError(
                f"{workers_option} sizes the local cluster; with --scheduler the cluster has "
                "its own"
            )
        try:
            check_address(scheduler)
            handshake(scheduler, CONNECT_S)
            client = Client(scheduler, timeout=CONNECT_S)
        except RigInterrupted:  # Ctrl-C while connecting: an interrupted sweep, not a bad address
            raise
        except Exception as exc:  # also a peer speaking another protocol (MemoryError)
            why = " ".join(str(exc).split())[:200] or type(exc).__name__
            if not isinstance(exc, Unusable):  # said already what it is
                why = f"cannot connect (is it a Dask scheduler?): {why}"
            raise ControllerConfigError(f"--scheduler {scheduler}: {why}") from None
        try:
            client.wait_for_workers(1, timeout=WORKER_WAIT_S)
        except TimeoutError:
            client.close()
            raise ControllerConfigError(
                f"--scheduler {scheduler}: no worker joined within {WORKER_WAIT_S:g} s "
                f"(start one: dask worker {scheduler} --nthreads 1)"
            ) from None
        return Cluster(client)
    n = machine_workers() if workers is None else workers
    if not 1 <= n <= MAX_WORKERS:
        raise ControllerConfigError(f"{workers_option} must be 1..{MAX_WORKERS}, got {n}")
    env = {"env": {**WORKER_ENV, **(worker_env or {})}} if processes else {}  # threads: ours
    # worker processes ignore the terminal's Ctrl-C; threads need not (and a Ctrl-C then is heeded)
    with _workers_ignore_sigint() if processes else contextlib.nullcontext():
        local = LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=processes,
            protocol="tcp://",
            host="127.0.0.1",
            dashboard_address=None,
            worker_dashboard_address=None,
            silence_logs=logging.ERROR,
            # its HTTP server on a free port: 8787 may be another sweep's (a warning each time)
            scheduler_kwargs={"dashboard": False, "dashboard_address": "127.0.0.1:0"},
            **env,
        )
    return Cluster(Client(local), local)
