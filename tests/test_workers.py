"""A real `dask scheduler` + `dask worker --preload workers/geocoder_preload.py` cluster."""

import os
import subprocess
import sys
import time
from pathlib import Path

import dask
import dask.array as da
import numpy as np
import pytest
import yaml
from distributed import Client

from geocoder import register
from geocoder.runtime import (
    IN_FLIGHT_PER_THREAD,
    THREADS_TTL_S,
    WORKER_CONFIG,
    WORKER_ENV,
    compute_as_completed,
    local_cluster,
    shared_input,
)
from geocoder.scene import write_geotiff
from geocoder.simulate.texture import synthetic_ortho
from geocoder.simulate.warp import make_pair

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.cluster


@pytest.fixture
def preloaded_cluster(tmp_path):
    bindir = Path(sys.executable).parent
    sched_file = tmp_path / "scheduler.json"
    env = dict(os.environ, DASK_CONFIG=str(ROOT / "workers" / "dask.yaml"))
    procs = [subprocess.Popen([bindir / "dask", "scheduler", "--port", "0", "--dashboard-address", ":0", "--scheduler-file", sched_file],
                              env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        for _ in range(300):
            if sched_file.exists():
                break
            time.sleep(0.1)
        procs.append(subprocess.Popen([bindir / "dask", "worker", "--scheduler-file", sched_file, "--nthreads", "1",
                                       "--preload", ROOT / "workers" / "geocoder_preload.py"],
                                      env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True))
        with Client(scheduler_file=str(sched_file), timeout=60) as c:
            c.wait_for_workers(1, timeout=120)
            yield c
    finally:
        for p in reversed(procs):
            p.terminate()
            p.wait(timeout=30)


def _profiler(client: Client) -> set[tuple[bool, bool]]:
    """(profiler enabled in the configuration, profiler callbacks scheduled) of every worker."""
    return set(client.run(
        lambda dask_worker: (__import__("dask").config.get("distributed.worker.profile.enabled"),
                             "profile-cycle" in dask_worker.periodic_callbacks)
    ).values())


def test_register_on_preloaded_workers(tmp_path, preloaded_cluster):
    c = preloaded_cluster
    assert all(v["NUMBA_NUM_THREADS"] == "1" for v in c.run(lambda: dict(os.environ)).values())
    assert all(v.get("MALLOC_MMAP_THRESHOLD_") == WORKER_ENV["MALLOC_MMAP_THRESHOLD_"]
               for v in c.run(lambda: dict(os.environ)).values()), "workers/dask.yaml sets glibc's mmap threshold before the worker starts"
    assert _profiler(c) == {(False, False)}, "workers/dask.yaml turns the profiler off"
    src = synthetic_ortho((352, 352), seed=3)
    pair = make_pair(src, shape=(256, 256), seed=3, margin=48)
    write_geotiff(tmp_path / "b.tif", pair.base)
    write_geotiff(tmp_path / "d.tif", pair.distorted)
    ds = register(tmp_path / "b.tif", tmp_path / "d.tif", tile=128, client=c, out=tmp_path / "o.zarr")
    inside = ds.status.values > 0
    rmse = np.sqrt(np.mean(((ds.dx.values - pair.dx) ** 2 + (ds.dy.values - pair.dy) ** 2)[inside]))
    assert rmse < 0.1


def test_local_cluster_workers_keep_no_profile_history():
    """The profiler's history grows with the job's length, not the tile size."""
    with local_cluster(1) as cluster, Client(cluster) as c:
        assert c.submit(sum, range(10)).result() == 45
        assert _profiler(c) == {(False, False)}
        # glibc reads it only at start: it must come through the nanny's pre-spawn environment
        assert set(c.run(lambda: os.environ.get("MALLOC_MMAP_THRESHOLD_")).values()) == {WORKER_ENV["MALLOC_MMAP_THRESHOLD_"]}
        assert dask.config.get("distributed.worker.profile.enabled") is True, "the client's own configuration is untouched"


def test_workers_dask_yaml_matches_the_local_worker_configuration():
    config = yaml.safe_load((ROOT / "workers" / "dask.yaml").read_text())
    for key, value in WORKER_CONFIG.items():
        node = config
        for part in key.split("."):
            node = node[part]
        assert node == value, key


def _square(i: int) -> int:
    return i * i


def _squares(n: int) -> dict:
    """Independent tasks whose Dask keys are their names, so the client's futures name them."""
    return {f"t{i}": dask.delayed(_square, pure=False)(i, dask_key_name=f"t{i}") for i in range(n)}


def _running_on_worker(dask_worker=None) -> int:
    """Tasks the worker's threads still run, those the scheduler has already forgotten included
    (a cancelled task runs on until it returns)."""
    return len(dask_worker.state.executing) + len(dask_worker.state.long_running)


def _wait_idle(client: Client, timeout: float = 60.0) -> None:
    """Until both workers of the session's cluster are up and run nothing: a test that counts where
    its tasks run needs them free. A task an earlier test gave up may still be finishing on one;
    the scheduler no longer lists it, so each worker is asked (in CI the scheduler's view alone let
    a test start beside such a task, and work stealing then moved all four of its tasks to the other
    worker)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if (sum(client.nthreads().values()) == 2 and not any(client.processing().values())
                and not any(client.run(_running_on_worker).values())):
            return
        time.sleep(0.05)
    pytest.fail(f"the session's two workers were not idle within {timeout:.0f} s")


def _compute_counting(client: Client, tasks: dict, on_yield=None) -> tuple[dict, list[int]]:
    """Results, and at every yield how many tasks were submitted and not yet yielded.

    Counted from the client's futures of these tasks minus the keys already yielded, so a release
    still on its way to the scheduler does not count, the count does not depend on when tasks
    finish, and a future an earlier test of the session still holds does not count either.
    """
    results: dict = {}
    in_flight: list[int] = []
    with client.as_current():
        for n, (key, value) in enumerate(compute_as_completed(tasks)):
            results[key] = value
            if on_yield is not None:
                on_yield(n)
            in_flight.append(len((set(client.futures) & set(tasks)) - set(results)))
    return results, in_flight


def test_tile_tasks_of_their_own_run_a_window_per_thread(client):
    """A finished task's result and inputs stay on its worker until the client fetches
    them, so independent tile tasks are submitted a few per worker thread, not all at once."""
    results, in_flight = _compute_counting(client, _squares(80))
    assert results == {f"t{i}": i * i for i in range(80)}
    assert max(in_flight) <= IN_FLIGHT_PER_THREAD * sum(client.nthreads().values()) < 80


def test_tile_tasks_sharing_inputs_run_as_one_graph(client):
    shared = dask.delayed(_square, pure=False)(3)
    tasks = {f"t{i}": dask.delayed(int.__add__)(shared, i, dask_key_name=f"t{i}") for i in range(40)}
    results, in_flight = _compute_counting(client, tasks)
    assert results == {f"t{i}": 9 + i for i in range(40)}
    assert in_flight[0] == 39, "submitted together, the shared input computed once"


def test_the_window_follows_workers_that_join_during_a_stage():
    with local_cluster(1) as cluster, Client(cluster) as c:
        def grow(n: int) -> None:
            if n == 0:
                cluster.scale(2)
                c.wait_for_workers(2, timeout=120)
                # the scheduler counts the new worker's thread, and the count compute_as_completed
                # keeps is older than THREADS_TTL_S (without both, one run in ten kept a window of 8)
                deadline = time.monotonic() + 120
                while sum(c.nthreads().values()) < 2 and time.monotonic() < deadline:
                    time.sleep(0.05)
                time.sleep(THREADS_TTL_S)

        results, in_flight = _compute_counting(c, _squares(4 * IN_FLIGHT_PER_THREAD), on_yield=grow)
    assert results == {f"t{i}": i * i for i in range(4 * IN_FLIGHT_PER_THREAD)}
    assert in_flight[0] <= IN_FLIGHT_PER_THREAD, "a window per thread of the one worker"
    assert max(in_flight) > IN_FLIGHT_PER_THREAD, "the joining worker's thread gets tasks too"


def _pid_block(table: np.ndarray, seconds: float) -> np.ndarray:
    time.sleep(seconds)
    return np.full((1, 1), os.getpid() + 0 * int(table.sum()))


def test_a_shared_input_does_not_draw_its_few_tasks_to_one_worker(client):
    """The tiles of a small scene reading one constant (fewer than the scheduler queues as root
    tasks): with the constant on one worker, three or four of the four ran there one after another."""
    _wait_idle(client)
    tab = shared_input(np.arange(60_000, dtype=np.float64), "table-x")
    blocks = da.map_blocks(_pid_block, tab, 0.1, chunks=((1, 1), (1, 1)), dtype=np.int64, name="pid-block-x")
    pids, counts = np.unique(blocks.compute(), return_counts=True)
    assert set(pids) == set(client.run(os.getpid).values()) and list(counts) == [2, 2]


def _wanted(key: str, dask_scheduler=None) -> bool:
    ts = dask_scheduler.tasks.get(key)
    return ts is not None and bool(ts.who_wants)


def _write_once_given_up(path: str, started: str, key: str) -> int:
    """Runs on until the caller has given this task up (cancelled it on the other's error), then
    writes its file: a running task that a cancel does not stop."""
    from distributed import Event, get_client

    Event(started).set()
    client = get_client()
    for _ in range(1200):  # at most a minute, should nothing cancel it
        if not client.run_on_scheduler(_wanted, key):
            break
        time.sleep(0.05)
    Path(path).write_text("written by a task that was running when the other failed")
    return 1


def _fail_once_started(started: str) -> int:
    from distributed import Event

    Event(started).wait(timeout=60)
    raise ValueError("boom")


def test_an_error_leaves_no_task_writing_behind_it(client, tmp_path):
    """The error reaches the caller only once the tasks still running have let go: the task
    that was running when the other failed has written its file by then, so nothing appears on
    disk after the caller has cleaned up."""
    name = tmp_path.name
    started = f"started-{name}"
    tasks = {"fail": dask.delayed(_fail_once_started, pure=False)(started, dask_key_name=f"fail-{name}"),
             "late": dask.delayed(_write_once_given_up, pure=False)(str(tmp_path / "late"), started, f"late-{name}",
                                                                    dask_key_name=f"late-{name}")}
    with client.as_current(), pytest.raises(ValueError, match="boom"):
        for _ in compute_as_completed(tasks):
            pass
    assert (tmp_path / "late").exists(), "the error came back while a task was still running"


def test_a_few_long_tasks_run_one_per_thread(client):
    """Four tiles on two threads: one each in flight, the next to whichever thread frees first
    (submitted together, each worker got two and the faster one idled at the end)."""
    _wait_idle(client)
    results, in_flight = _compute_counting(client, _squares(4))
    assert results == {f"t{i}": i * i for i in range(4)}
    assert max(in_flight) <= sum(client.nthreads().values()) == 2
