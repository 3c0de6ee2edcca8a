"""A cluster whose only worker died leaves the tasks waiting: ``Tasks.next`` (``hil sweep``,
``hil experiment``) says so on stderr after ``no_worker_s`` without a worker, one line naming
the scheduler, and keeps waiting; the task runs once a worker joins again."""

from __future__ import annotations

import logging
import re

import pytest

pytest.importorskip("distributed")

from distributed import Client, LocalCluster

from rt_controller.sweep.executor import Cluster, Tasks


def double(x: int) -> int:
    return 2 * x


def test_no_worker_is_said_and_the_task_waits_for_one() -> None:
    local = LocalCluster(
        n_workers=0,
        processes=False,
        protocol="tcp://",
        host="127.0.0.1",
        dashboard_address=None,
        silence_logs=logging.ERROR,
    )
    cluster = Cluster(Client(local), local)
    said: list[str] = []

    def say(line: str) -> None:  # a worker joins once the wait was said: next() returns
        said.append(line)
        if len(said) == 1:
            local.scale(1)

    try:
        with Tasks(cluster, "t", no_worker_s=0.3, say=say) as tasks:
            tasks.submit("item", double, 21, key="one")
            assert tasks.next() == ("item", 42, None)
    finally:
        cluster.close()
    address = re.escape(local.scheduler_address)
    line = rf"no worker in the cluster at {address} for [0-9.]+ s; waiting "
    line += r"\(Ctrl-C keeps the finished rows\)"
    assert said and re.fullmatch(line, said[0]), said
