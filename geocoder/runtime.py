"""Where work runs: an existing ``distributed.Client``, a scheduler address, or a local cluster."""

from __future__ import annotations

import json
import logging
import os
import time
from contextlib import contextmanager
from typing import Any, Iterator

import dask
from distributed import Client, LocalCluster, WorkerPlugin, as_completed

from ._version import __version__
from .errors import EnvironmentFailure, GeocoderError
from .interrupts import raise_dropped_interrupt

log = logging.getLogger(__name__)

#: Environment of every worker process: one thread per numeric library (parallelism comes from
#: tasks), a bounded GDAL block cache (by default 5 % of the machine's memory, which fills
#: with every tile read, so a worker's memory would grow with the scene), and glibc's heap.
#: Dask's nanny sets ``MALLOC_TRIM_THRESHOLD_`` to 64 KiB (freed memory goes back to the system
#: at once), which also freezes glibc's mmap threshold at 128 KiB: every larger temporary (a
#: 512² float64 tile is 2 MiB) was then a fresh mapping, and every task's arrays were mapped
#: and zero-filled page by page again on first touch, which costs ~10 us per 4 KiB page in
#: this virtual machine (kernels ran up to twice as slow as in a plain process). Arrays up to
#: 32 MiB (glibc's own dynamic limit) come from the heap, and up to 256 MiB of freed heap stays
#: with the process for the next task: a worker's memory is still bounded by its tasks (not the
#: scene), at ~0.2 GiB more; the 2048² dense job (tile 1024) ran 7.3-7.4 -> 6.5-6.8 s, peak
#: worker memory 0.74 -> 0.90-1.02 GiB (two interleaved runs each, issue 12's notes). The heap
#: still grew, and was trimmed, by the few pages each request needed, so a task larger than the
#: last one faulted its new pages in one by one again (a 2048² dense job: 120-190 thousand minor
#: faults and 1.2-2.4 s of system time in the workers, every run); ``MALLOC_TOP_PAD_`` grows and
#: keeps it 256 MiB at a time: 17-30 thousand faults and 0.5-0.8 s after a worker's first job;
#: the job 7.6 -> 6.9 s and 7.61 -> 7.42 s (two series of runs alternated on fresh clusters),
#: 4096² 26.5 -> 24.8 s, peak worker memory about the same (issue 12's notes); mmap's threshold
#: raised to 256 MiB changed neither time nor memory (three alternated pairs of clusters). glibc
#: reads all three when the process starts, so they must reach it through the environment it
#: starts with (the nanny's ``pre-spawn-environ``, see :data:`WORKER_CONFIG`).
#: This is the one definition: the preload (``workers/geocoder_preload.py``) imports it, and the
#: ``ENV`` of ``workers/Dockerfile`` must repeat it (tests/test_worker_env.py compares them).
WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1",
              "GDAL_CACHEMAX": "16", "MALLOC_MMAP_THRESHOLD_": "33554432", "MALLOC_TRIM_THRESHOLD_": "268435456", "MALLOC_TOP_PAD_": "268435456"}

#: Dask configuration of every worker (``workers/dask.yaml`` must hold it too; tests/test_worker_env.py
#: compares them). The statistical
#: profiler keeps up to 1000 one-second cycles of call-stack trees per worker, so a worker's
#: memory grew with the job's length rather than the tile (six 1024² dense jobs in a row:
#: peak 436 -> 444 MiB with it, 428 -> 432 without). Turn it back on to tune
#: (``DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED=True``).
WORKER_CONFIG = {"distributed.worker.profile.enabled": False,
                 **{f"distributed.nanny.pre-spawn-environ.{k}": WORKER_ENV[k]
                    for k in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_")}}


def local_cluster(n_workers: int | None = None, *, memory_limit: str | None = "auto") -> LocalCluster:
    """A local cluster of worker processes sized to the machine, one thread each.

    Parallelism comes from tasks, not from threads inside kernels, so every worker runs
    one thread (and one BLAS thread). ``n_workers`` defaults to the option ``n_workers``
    (:func:`geocoder.set_options`, Dask config ``geocoder.n_workers``), else one per CPU. Workers run with :data:`WORKER_ENV` and
    :data:`WORKER_CONFIG` (a nanny hands its configuration to the worker it restarts).
    """
    from .options import get_option

    n = n_workers or get_option("n_workers") or max(1, os.cpu_count() or 1)
    # a task's error reaches the client, which reports it; when the caller keeps Dask's own
    # errors quiet (the CLI unless -vv) the workers do not also log it with its traceback
    quiet = logging.getLogger("distributed").getEffectiveLevel() >= logging.ERROR
    with dask.config.set(WORKER_CONFIG), _interrupts_ignored_by_children():
        return LocalCluster(
            silence_logs=logging.CRITICAL if quiet else logging.WARNING,
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            memory_limit=memory_limit,
            dashboard_address=":0",
            env=dict(WORKER_ENV),
        )


@contextmanager
def _interrupts_ignored_by_children() -> Iterator[None]:
    """Processes started inside the block ignore SIGINT (an ignored signal stays ignored in a child).

    A Ctrl-C in a terminal reaches every process of the foreground group: the local
    cluster's workers would each print a KeyboardInterrupt traceback while the client, which
    handles the interrupt, shuts them down anyway. Outside the main thread nothing changes.
    """
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


class IgnoreInterrupts(WorkerPlugin):
    """Worker plugin: the worker process ignores SIGINT (its client handles Ctrl-C and stops it).

    Registered on the local clusters geocoder starts, so that a worker its nanny restarts
    ignores it too.
    """

    name = "geocoder-ignore-interrupts"

    def setup(self, worker) -> None:
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)


class QuietRawFrames(WorkerPlugin):
    """Worker plugin: rasterio's ``NotGeoreferencedWarning`` is not shown.

    geocoder reads a file without georeference as a raw scanner frame on purpose (the scene
    says so in ``attrs["georeferenced"]``); the warning, printed by every worker that reads
    such a file, told the user nothing. Only that category is filtered.
    """

    name = "geocoder-quiet-raw-frames"

    def setup(self, worker) -> None:
        import warnings

        from rasterio.errors import NotGeoreferencedWarning

        warnings.filterwarnings("ignore", category=NotGeoreferencedWarning)


def connect(scheduler: str, *, timeout: float = 10) -> Client:
    """A client of a running cluster.

    ``scheduler`` is an address (``tcp://host:8786``, ``tls://...``; TLS certificates come
    from Dask's configuration, ``DASK_DISTRIBUTED__COMM__TLS__*``) or the ``cluster.json``
    written by ``geocoder cluster up`` (address and certificates).

    Raises
    ------
    GeocoderError
        On an address that cannot be parsed or TLS without certificates (exit code 2).
    EnvironmentFailure
        When the scheduler does not answer within ``timeout`` seconds (exit code 3).
    """
    security = None
    address = scheduler
    if os.path.isfile(scheduler):
        try:
            with open(scheduler) as f:
                info = json.load(f)
            address = info["address"]
        except (OSError, ValueError, KeyError) as exc:
            raise GeocoderError(f"{scheduler}: not a cluster file written by 'geocoder cluster up' ({exc})") from exc
        if info.get("tls"):
            from .certs import client_security

            security = client_security(info["tls"])
    if str(address).startswith("tls://") and security is None and not dask.config.get("distributed.comm.tls.ca-file", None):
        raise GeocoderError(
            f"{address}: TLS needs certificates: pass the cluster.json of 'geocoder cluster up' as --scheduler, or set "
            "DASK_DISTRIBUTED__COMM__TLS__CA_FILE, DASK_DISTRIBUTED__COMM__TLS__CLIENT__CERT and ..._CLIENT__KEY"
        )
    try:
        client = Client(address, security=security, timeout=timeout)
    except (OSError, TimeoutError) as exc:
        raise EnvironmentFailure(address, f"the Dask scheduler does not answer ({_first_line(exc)}); is it running?") from exc
    except (ValueError, TypeError) as exc:  # an address or a security setting Dask cannot use
        raise GeocoderError(f"{address}: not a usable Dask scheduler address ({_first_line(exc)})") from exc
    try:
        check_versions(client)
    except BaseException:
        client.close()
        raise
    return client


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _geocoder_version() -> str:
    return __version__


def check_versions(client: Client, *, wait: float = 60) -> None:
    """Fail with a clear message unless the workers run this client's geocoder version."""
    try:
        client.wait_for_workers(1, timeout=wait)
    except TimeoutError:
        raise GeocoderError(f"the scheduler {client.scheduler.address} has no workers (waited {wait:.0f} s)") from None
    mine = _geocoder_version()
    theirs = client.run(_geocoder_version)
    wrong = {w: v for w, v in theirs.items() if v != mine}
    if wrong:
        listed = ", ".join(f"{w} has {v}" for w, v in sorted(wrong.items()))
        raise GeocoderError(f"geocoder version mismatch: this client has {mine}; {listed}")


@contextmanager
def dask_client(client: Client | None = None, scheduler: str | None = None, n_workers: int | None = None) -> Iterator[Client]:
    """Yield a client that is the current default for ``.compute()`` inside the block.

    Order of choice: ``client``; ``scheduler`` (an address or a ``cluster.json``);
    ``DASK_SCHEDULER_ADDRESS``; otherwise a new local cluster that is closed on exit.
    """
    if client is not None:
        with client.as_current():
            yield client
        return
    address = scheduler or os.environ.get("DASK_SCHEDULER_ADDRESS")
    if address:
        with connect(address) as c, c.as_current():
            c.register_plugin(QuietRawFrames())
            log.debug("Dask scheduler %s; dashboard %s", c.scheduler.address, c.dashboard_link)
            yield c
        return
    cluster = local_cluster(n_workers)
    try:
        with Client(cluster) as c, c.as_current():
            c.register_plugin(IgnoreInterrupts())
            c.register_plugin(QuietRawFrames())
            log.debug("local Dask cluster with %d workers; dashboard %s", len(cluster.workers), c.dashboard_link)
            yield c
    finally:
        close_local_cluster(cluster)


def close_local_cluster(cluster: LocalCluster, timeout: float | None = None) -> None:
    """Close ``cluster``; if closing times out, say so instead of raising.

    Closing must not replace the job's own outcome (an interrupt, an error, a committed output)
    with Dask's timeout: a worker busy in a kernel, or one just killed on a loaded machine,
    can take longer to end than the nanny waits for (5 s, the last 1 s after its SIGKILL). The
    worker processes are daemons of this process: what is left of them ends when it exits.

    Parameters
    ----------
    cluster : the local cluster (its workers are processes started by this one).
    timeout : seconds for the whole close (Dask's default when None).
    """
    import asyncio

    pids = [pid for pid in (getattr(w, "pid", None) for w in cluster.workers.values()) if pid]
    try:
        cluster.close(timeout=timeout)
    except (TimeoutError, asyncio.TimeoutError):
        log.warning("the local Dask cluster did not close in time; its worker processes (pid %s) end with this process",
                    ", ".join(map(str, pids)) or "none")


def is_cluster_failure(exc: BaseException) -> bool:
    """Whether ``exc`` is Dask losing its scheduler or workers (the cluster failed, not the input)."""
    import asyncio

    from distributed.client import FutureCancelledError
    from distributed.comm.core import CommClosedError

    try:  # the client closed itself on losing the scheduler; the next call on it raises this
        from distributed.client import ClosedClientError
    except ImportError:  # pragma: no cover - older distributed
        ClosedClientError = CommClosedError

    try:
        from distributed.scheduler import KilledWorker
    except ImportError:  # pragma: no cover
        KilledWorker = CommClosedError
    if isinstance(exc, (CommClosedError, ClosedClientError, FutureCancelledError, KilledWorker, asyncio.CancelledError)):
        return True
    # a call to the scheduler after the client closed its connections (it lost the scheduler)
    if type(exc) is RuntimeError and str(exc) == "ConnectionPool is closed":
        return True
    # the client's reconnection gave up: a plain OSError from distributed.comm.core.connect
    return type(exc) is OSError and exc.errno is None and str(exc).startswith("Timed out trying to connect")


def current_client() -> Client | None:
    """The distributed client of the running job, if any."""
    try:
        from distributed import default_client

        return default_client()
    except ValueError:
        return None


def shared_input(value: Any, name: str) -> Any:
    """``value`` as the one input of many tile tasks (a ``Delayed``), held by every worker.

    The scheduler places a task with inputs only on the workers that hold them: a constant
    computed on one worker drew every task that reads it to that worker when the tasks were
    too few to count as root tasks (the four tiles of a 2048² job's line estimates, and their
    resampling and writing after them, ran one after another on one of two workers). On a
    distributed client the value is therefore scattered to every worker; without one (or
    without workers yet, where a broadcast would wait for them) it is a plain ``dask.delayed``
    named ``name``.
    """
    client = current_client()
    if client is None or not client.scheduler_info().get("workers"):
        return dask.delayed(value, pure=True, name=name)
    return dask.delayed(client.scatter(value, broadcast=True, hash=False))


#: Single-task items :func:`compute_as_completed` keeps in flight per worker thread (a bound on the
#: results and inputs waiting on a worker, and enough queued work to hide the round trips).
IN_FLIGHT_PER_THREAD = 8
#: Seconds :func:`compute_as_completed` trusts the scheduler's count of worker threads: asking on
#: every finished task cost a round trip each (~10 ms; 2.5 s of a 23 s four-scene mosaic).
THREADS_TTL_S = 0.5
#: Fewer tasks than this many per worker thread are kept one per thread in flight (see
#: :func:`compute_as_completed`); from ``FEW_PER_THREAD * IN_FLIGHT_PER_THREAD`` on, the full window.
FEW_PER_THREAD = 4


def compute_as_completed(tasks: dict[str, Any]) -> Iterator[tuple[str, Any]]:
    """Compute ``tasks`` (key -> dask collection); yield ``(key, result)`` as each finishes.

    On a distributed client results arrive in completion order. Tasks that share inputs
    run as one graph (common inputs computed once). Tasks that are each a single task of
    their own (inputs embedded, data read by the task) are kept :data:`IN_FLIGHT_PER_THREAD`
    per worker thread (of the moment) in flight (fewer when the tasks are few per thread:
    :data:`FEW_PER_THREAD`), the next submitted as each finishes: a
    finished result waits on its worker, with its task's inputs, until the client has fetched
    it, so submitting all at once let a busy client leave a backlog that grew with the number
    of tiles; too few in flight leave a worker idle for a round trip after each short task
    (a 100-scene mosaic's ~2,000 correspondence tasks of ~15 ms: 41.3 s with 2, 35.9 s with 8). Without a client the tasks are computed together by the current
    Dask scheduler and yielded in key order.
    """
    raise_dropped_interrupt()  # a Ctrl-C Python could not raise where it came (geocoder.interrupts)
    if not tasks:
        return
    client = current_client()
    if client is None:
        yield from zip(tasks, dask.compute(*tasks.values()))
        return
    items = list(tasks.items())
    shared = not all(_single_task(t) for _, t in items)
    running: dict[int, tuple[str, Any]] = {}  # id(future) -> (key, future)

    asked = [-float("inf"), 1]  # when the scheduler was last asked, and its answer

    def threads() -> int:  # a round trip to the scheduler, so asked at most every THREADS_TTL_S
        if time.monotonic() - asked[0] > THREADS_TTL_S:
            asked[:] = [time.monotonic(), max(1, sum(client.nthreads().values()))]
        return asked[1]

    # a stage of few tasks per thread (a handful of tiles, each seconds long) runs one per thread,
    # the next to the thread that frees first: the scheduler hands every worker its share at
    # submission and does not move a queued task, so 4 tiles on 2 workers waited on the slower pair
    per_thread = max(1, min(IN_FLIGHT_PER_THREAD, len(items) // (FEW_PER_THREAD * threads())))

    def room() -> int:  # asked again as each task finishes: workers may join or leave
        if shared:
            return len(items)
        return per_thread * threads() - len(running)

    n = room()
    first = client.compute([t for _, t in items[:n]])
    running.update((id(f), (k, f)) for (k, _), f in zip(items[:n], first))
    queue = as_completed(first, with_results=True)
    del first
    rest = iter(items[n:])
    tasks_of = dict(items)
    try:
        for fut, value in queue:
            raise_dropped_interrupt()
            if fut.status == "cancelled" and isinstance(value, BaseException):
                raise value  # as_completed hands a cancelled future's error over as its result (scheduler lost)
            key, _ = running.pop(id(fut))
            fut.release()
            for _, (k, task) in zip(range(room()), rest):
                f = client.compute(task)
                running[id(f)] = (k, f)
                queue.add(f)
            yield key, value
    finally:
        if running:  # an error, here or in the caller: nothing may keep writing after it
            cancel_and_settle(client, [f for _, f in running.values()], [tasks_of[k] for k, _ in running.values()])


def cancel_and_settle(client: Client, futures: list, collections: list, timeout: float = 10.0) -> None:
    """Cancel ``futures`` and wait, at most ``timeout`` s, until no worker still runs a task of
    ``collections`` (the dask collections they compute).

    Cancelling releases a task on the scheduler but does not stop one that a worker is
    running: a store task of a failed ingest finished its chunk after the client had removed
    the job's directory, and recreated part of it. Waiting for the workers to let go first
    keeps an error from leaving anything behind. Best effort: a client that cannot reach its
    workers (the scheduler is lost) does not wait.
    """
    for fut in futures:
        try:
            fut.cancel()
        except Exception:  # noqa: BLE001 - the client closed on losing its scheduler: the caller's error stands
            return
    keys = {str(k) for c in collections for k in c.__dask_graph__().keys()}
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            running = client.run(_executing_keys, on_error="ignore")
        except Exception:  # noqa: BLE001 - the scheduler or the workers are gone: nothing to wait for
            return
        if not any(k in keys for ks in running.values() if isinstance(ks, list) for k in ks):
            return
        time.sleep(0.05)


def _executing_keys(dask_worker) -> list[str]:
    return [str(ts.key) for ts in dask_worker.state.executing]


def _single_task(collection: Any) -> bool:
    graph = collection.__dask_graph__()
    return graph is not None and len(graph) == 1
