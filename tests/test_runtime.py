"""Where work runs: the local cluster's shutdown."""

from __future__ import annotations

import logging
import time

import psutil

from geocoder.runtime import close_local_cluster, local_cluster


def _ended(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def test_a_local_cluster_that_does_not_close_in_time_is_killed_without_an_error(caplog):
    """Closing must not replace a job's outcome (Ctrl-C, a committed output) with Dask's TimeoutError.

    A loaded machine made a nanny wait longer than its 1 s for a SIGKILLed worker to be reaped:
    the CLI then ended with that traceback and exit code 1 instead of 130. Here the whole close
    is given far less time than any worker takes to stop.
    """
    cluster = local_cluster(2)
    pids = [w.pid for w in cluster.workers.values()]
    assert len(pids) == 2 and all(pids)
    with caplog.at_level(logging.WARNING, logger="geocoder.runtime"):
        close_local_cluster(cluster, timeout=0.001)
    assert "did not close in time; its 2 worker process(es) are killed" in caplog.text
    deadline = time.monotonic() + 30
    while not all(map(_ended, pids)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert all(map(_ended, pids)), [psutil.Process(p).status() for p in pids if not _ended(p)]


def test_a_local_cluster_closes_quietly(caplog):
    cluster = local_cluster(1)
    pids = [w.pid for w in cluster.workers.values()]
    with caplog.at_level(logging.WARNING, logger="geocoder.runtime"):
        close_local_cluster(cluster)
    assert not [r for r in caplog.records if r.name == "geocoder.runtime"] and all(map(_ended, pids))
