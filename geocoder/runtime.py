"""Where work runs: an existing ``distributed.Client``, a scheduler address, or a local cluster."""

from __future__ import annotations

import logging
import os
from contextlib import contextmanager
from typing import Iterator

from distributed import Client, LocalCluster

log = logging.getLogger(__name__)


def local_cluster(n_workers: int | None = None, *, memory_limit: str | None = "auto") -> LocalCluster:
    """A local cluster of worker processes sized to the machine, one thread each.

    Parallelism comes from tasks, not from threads inside kernels, so every worker runs
    one thread (and one BLAS thread).
    """
    n = n_workers or max(1, os.cpu_count() or 1)
    env = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
    return LocalCluster(
        n_workers=n,
        threads_per_worker=1,
        processes=True,
        memory_limit=memory_limit,
        dashboard_address=":0",
        env=env,
    )


@contextmanager
def dask_client(client: Client | None = None, scheduler: str | None = None, n_workers: int | None = None) -> Iterator[Client]:
    """Yield a client that is the current default for ``.compute()`` inside the block.

    Order of choice: ``client``; ``scheduler`` (an address); ``DASK_SCHEDULER_ADDRESS``;
    otherwise a new local cluster that is closed on exit.
    """
    if client is not None:
        with client.as_current():
            yield client
        return
    address = scheduler or os.environ.get("DASK_SCHEDULER_ADDRESS")
    if address:
        with Client(address) as c, c.as_current():
            yield c
        return
    with local_cluster(n_workers) as cluster, Client(cluster) as c, c.as_current():
        log.info("local Dask cluster with %d workers; dashboard %s", len(cluster.workers), c.dashboard_link)
        yield c
