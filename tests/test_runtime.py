"""Where work runs: the local cluster's shutdown."""

from __future__ import annotations

import logging
import subprocess
import sys

import psutil

from geocoder.runtime import close_local_cluster, local_cluster

#: A process that starts a local cluster and gives closing it far less time than any worker
#: takes to stop, then exits as the command line does after a job.
_TIMED_OUT_CLOSE = """
import logging, sys
logging.basicConfig(level=logging.WARNING, stream=sys.stdout, format="%(name)s: %(message)s")
from geocoder.runtime import close_local_cluster, local_cluster
cluster = local_cluster(2)
print("PIDS", *[w.pid for w in cluster.workers.values()], flush=True)
close_local_cluster(cluster, timeout=0.001)
print("RETURNED", flush=True)
"""


def _ended(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def test_a_cancelled_close_of_a_local_cluster_is_a_warning_not_an_error():
    """Closing must not replace a job's outcome (Ctrl-C, a committed output) with Dask's TimeoutError.

    A loaded machine made a nanny wait longer than its 1 s for a SIGKILLed worker to be reaped:
    the CLI then ended with that traceback and exit code 1 instead of one line and 130. The
    workers left end with the process.
    """
    r = subprocess.run([sys.executable, "-c", _TIMED_OUT_CLOSE], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "RETURNED" in r.stdout, r.stdout + r.stderr
    # the only traceback allowed: a worker process a nanny was still spawning as the process
    # exited fails to unpickle its start-up state (multiprocessing's, not the close; seen once in 5 runs)
    tracebacks = r.stderr.split("Traceback (most recent call last):")[1:]
    assert all("multiprocessing/spawn.py" in t and "_rebuild" in t for t in tracebacks), r.stderr
    assert "TimeoutError" not in r.stderr, r.stderr
    pids = [int(p) for p in r.stdout.split("PIDS", 1)[1].splitlines()[0].split()]
    assert len(pids) == 2
    assert f"geocoder.runtime: the local Dask cluster did not close in time; its worker processes (pid {pids[0]}, {pids[1]})" \
        in r.stdout, r.stdout
    procs = []
    for pid in pids:
        try:
            procs.append(psutil.Process(pid))
        except psutil.NoSuchProcess:
            pass
    _, alive = psutil.wait_procs(procs, timeout=30)
    assert not [p for p in alive if p.status() != psutil.STATUS_ZOMBIE], alive


def test_a_local_cluster_closes_quietly(caplog):
    cluster = local_cluster(1)
    pids = [w.pid for w in cluster.workers.values()]
    with caplog.at_level(logging.WARNING, logger="geocoder.runtime"):
        close_local_cluster(cluster)
    assert not [r for r in caplog.records if r.name == "geocoder.runtime"] and all(map(_ended, pids))
