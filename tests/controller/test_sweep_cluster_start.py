"""A local Dask cluster's start (``hil sweep``, ``hil experiment``) and the user's Ctrl-C."""

from __future__ import annotations

import os
import signal
import time

import pytest

distributed = pytest.importorskip("distributed")

from rt_controller.sweep.cluster import open_cluster  # noqa: E402


def test_ctrl_c_while_a_cluster_of_threads_starts_is_heeded(monkeypatch) -> None:
    """Only worker processes need SIGINT ignored while they start (they keep it); a cluster of
    threads (``hil experiment``'s) started with it ignored, and a Ctrl-C then was lost."""

    def interrupted_start(**_kw):
        os.kill(os.getpid(), signal.SIGINT)  # the user's Ctrl-C while the cluster starts
        time.sleep(0.5)  # Python's handler raises here, at the latest
        raise AssertionError("the Ctrl-C was not heeded")

    monkeypatch.setattr(distributed, "LocalCluster", interrupted_start)
    with pytest.raises(KeyboardInterrupt):
        open_cluster(1, processes=False)
