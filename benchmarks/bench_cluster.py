"""Per-worker peak memory against scene size, and wall time with 1 and 2 workers.

The whole register job (ingest, interest points, correspondence, dense matching or not,
resampling, writing) on simulated pairs (procedural ortho + known warp), on a local cluster
of worker processes, each after a 256² warm-up job on the same cluster (the kernels compiled or
loaded from numba's cache). Worker memory is the resident set of every worker process, sampled
from outside (psutil) every 50 ms, so a busy worker is measured too.

    python benchmarks/bench_cluster.py                       # polynomial 2048/8192, dense 2048/4096
    python benchmarks/bench_cluster.py --dense-sizes 2048 8192 --workers 2
    python benchmarks/bench_cluster.py --sizes --dense-sizes 2048 1024x8192 --workers 2   # width only
    python benchmarks/bench_cluster.py --sizes --dense-sizes 2048 --workers 2 --trace   # which tasks set the peak
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import tempfile
import threading
import time
from pathlib import Path

import psutil
from affine import Affine
from distributed import Client, WorkerPlugin

from geocoder import register
from geocoder.progress import Progress
from geocoder.runtime import local_cluster
from geocoder.scene import write_geotiff
from geocoder.simulate.texture import synthetic_ortho
from geocoder.simulate.warp import make_pair


class WorkerPeak(Progress):
    """Peak resident memory (MiB) of each worker process while the block runs.

    Passed as the job's progress receiver, it also keeps the largest worker's peak per
    phase (``by_phase``, round numbers folded), to tell which stage sets the peak.
    """

    def __init__(self, pids: list[int], interval: float = 0.05) -> None:
        self.procs = [psutil.Process(p) for p in pids]
        self.interval = interval
        self.peak = dict.fromkeys(pids, 0.0)
        self.current = "start"
        self.by_phase: dict[str, float] = {}

    def phase(self, name: str, total: int, *, skipped: int = 0) -> None:
        self.current = re.sub(r"\s*\((round|pass) \d+\)|,?\s*\d+/\d+", "", name)

    def __enter__(self):
        self._stop = threading.Event()

        def poll():
            while not self._stop.is_set():
                for p in self.procs:
                    try:
                        rss = p.memory_info().rss / 2**20
                    except psutil.Error:
                        continue
                    self.peak[p.pid] = max(self.peak[p.pid], rss)
                    self.by_phase[self.current] = max(self.by_phase.get(self.current, 0.0), rss)
                self._stop.wait(self.interval)

        self._t = threading.Thread(target=poll, daemon=True)
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()


class TaskMemory(WorkerPlugin):
    """Which tasks raised a worker's high-water mark (``ru_maxrss``, kept by the kernel, so
    no sample is missed), and how much task data the worker held at that moment."""

    name = "task-memory"

    def setup(self, worker) -> None:
        self.worker = worker
        self.started: dict = {}
        self.rows: list[tuple] = []

    def transition(self, key, start, finish, **kwargs) -> None:
        if finish == "executing":
            self.started[key] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        elif start == "executing" and key in self.started:
            before = self.started.pop(key)
            after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
            if after > before:
                rss = psutil.Process().memory_info().rss
                held = len(self.worker.data), self.worker.state.nbytes / 2**20
                self.rows.append((str(key), before / 1024, after / 1024, rss / 2**20, *held))


def print_trace(client: Client, top: int = 8) -> None:
    """The tasks that set each worker's high-water mark, largest last."""
    for addr, rows in client.run(lambda dask_worker: dask_worker.plugins["task-memory"].rows).items():
        print(f"  {addr}: {len(rows)} tasks raised the peak; the last {top}:")
        for key, before, after, rss, n, mib in rows[-top:]:
            print(f"    {key[:60]:60s} {before:6.0f} -> {after:6.0f} MiB (rss after {rss:.0f}; holds {n} results, {mib:.1f} MiB)")


def shape_of(size: str) -> tuple[int, int]:
    """``"2048"`` -> (2048, 2048); ``"1024x8192"`` -> (rows, columns)."""
    h, _, w = size.partition("x")
    return int(h), int(w or h)


def make_scene(size: str, work: Path) -> tuple[Path, Path]:
    h, w = shape_of(size)
    name = f"{h}" if h == w else f"{h}x{w}"
    base, dist = work / f"base-{name}.tif", work / f"dist-{name}.tif"
    if not base.exists():
        margin = 48
        src = synthetic_ortho((h + 2 * margin, w + 2 * margin), seed=11)
        pair = make_pair(src, shape=(h, w), seed=11, max_displacement=15.0, margin=margin)
        write_geotiff(base, pair.base, transform=Affine(2, 0, 500000, 0, -2, 4000000), crs="EPSG:32633")
        write_geotiff(dist, pair.distorted)
    return base, dist


def run(size: str, workers: int, dense: bool, work: Path, tile: int, trace: bool = False) -> dict:
    base, dist = make_scene(size, work)
    out = work / f"out-{size}-{workers}-{dense}.zarr"
    with local_cluster(workers) as cluster, Client(cluster) as c:
        pids = list(c.run(os.getpid).values())
        # a small job first: the workers compile (or load from numba's cache) the kernels, as
        # for any job after the first on a running cluster (a fresh clone has no cache: 15-20 s)
        wb, wd = make_scene("256", work)
        register(wb, wd, out=work / f"warm-{workers}-{dense}.zarr", tile=128, dense=dense, client=c, resume=False,
                 overwrite=True, show_progress=False)
        if trace:
            c.register_plugin(TaskMemory())
        t0 = time.perf_counter()
        with WorkerPeak(pids) as mem:
            register(base, dist, out=out, tile=tile, dense=dense, client=c, resume=False, show_progress=mem)
        wall = time.perf_counter() - t0
        if trace:
            print_trace(c)
    h, w = shape_of(size)
    return {"wall": wall, "peak": max(mem.peak.values()), "mpx": h * w / 1e6 / wall, "by_phase": mem.by_phase}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", nargs="*", default=["2048", "8192"], help="scene sides (or ROWSxCOLS) for the polynomial job")
    ap.add_argument("--dense-sizes", nargs="*", default=["2048", "4096"], help="scene sides (or ROWSxCOLS) for the dense job")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--tile", type=int, default=512)
    ap.add_argument("--trace", action="store_true", help="print the tasks that raised each worker's memory high-water mark")
    ap.add_argument("--work", default=None, help="directory for the scenes (default: a temporary one)")
    args = ap.parse_args()
    work = Path(args.work or tempfile.mkdtemp(prefix="bench-cluster-"))
    work.mkdir(parents=True, exist_ok=True)
    print(f"tile {args.tile}; {os.cpu_count()} cores; scenes in {work}")
    print("| job | scene | workers | wall s | Mpx/s | peak worker MiB | vs smallest scene |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for dense, sizes in ((False, args.sizes), (True, args.dense_sizes)):
        first: dict[int, float] = {}  # per worker count: the first scene's peak
        for size in sizes:
            for w in args.workers:
                r = run(size, w, dense, work, args.tile, args.trace)
                first.setdefault(w, r["peak"])
                print(f"| {'dense' if dense else 'polynomial'} | {size if 'x' in size else size + '²'} | {w} | {r['wall']:.1f} | {r['mpx']:.2f} | "
                      f"{r['peak']:.0f} | {100 * (r['peak'] / first[w] - 1):+.1f} % |", flush=True)
                print("  peak by phase: " + ", ".join(f"{k} {v:.0f}" for k, v in r["by_phase"].items()), flush=True)
    print("\nwall-time ratio 1/2 workers is the row pairs above; memory is the largest worker's peak resident set.")


if __name__ == "__main__":
    main()
