"""The register job with its stores on local disk and on an object store (a local S3 server).

The S3 server is moto, running in this process on the same two cores as the workers: a
pessimistic stand-in for S3 or MinIO (every request is served by Python), so the ratio is an
upper bound of the object-store overhead, not a prediction of S3's. Prints a table: wall time,
pixels per second, objects the job wrote, and the time of the commit (for S3 a server-side
copy of every output object, root metadata last; locally a rename).

    python benchmarks/bench_storage.py --size 2048 --dense-size 1024
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from unittest import mock

from bench_cluster import make_scene  # the script's directory is on sys.path
from distributed import Client

from geocoder import register, storage
from geocoder.runtime import local_cluster
from geocoder.testing import local_s3


def count_objects(location: str) -> int:
    import fsspec

    fs, path = fsspec.core.url_to_fs(location)
    fs.invalidate_cache()
    return len(fs.find(path))


def run(size: str, dense: bool, root: str, work: Path, tile: int, client: Client) -> dict:
    base, dist = make_scene(size, work)
    out = storage.join(root, f"out-{size}-{dense}.zarr")
    commit = storage.commit_store
    timed = {}

    def timed_commit(tmp: str, final: str) -> None:
        timed["objects"] = count_objects(tmp)
        t = time.perf_counter()
        commit(tmp, final)
        timed["commit"] = time.perf_counter() - t

    t0 = time.perf_counter()
    with mock.patch.object(storage, "commit_store", timed_commit):
        register(base, dist, out=out, tile=tile, dense=dense, client=client, resume=False)
    wall = time.perf_counter() - t0
    h, _, w = size.partition("x")
    return {"wall": wall, "mpx": int(h) * int(w or h) / 1e6 / wall, **timed}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="2048", help="scene side for the polynomial job")
    ap.add_argument("--dense-size", default="1024", help="scene side for the dense job")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--tile", type=int, default=512)
    ap.add_argument("--work", default=None)
    args = ap.parse_args()
    work = Path(args.work or tempfile.mkdtemp(prefix="bench-storage-"))
    work.mkdir(parents=True, exist_ok=True)
    print(f"tile {args.tile}; {args.workers} worker processes; local disk vs moto S3 in this process")
    print("| job | scene | store | wall s | Mpx/s | output objects | commit s | S3 / local |")
    print("|---|---:|---|---:|---:|---:|---:|---:|")
    with local_s3("bench") as bucket, local_cluster(args.workers) as cluster, Client(cluster) as c:
        run("512", True, str(work), work, 256, c)  # numba compiles in the workers before anything is timed
        for dense, size in ((False, args.size), (True, args.dense_size)):
            make_scene(size, work)
            local = run(size, dense, str(work), work, args.tile, c)
            remote = run(size, dense, bucket, work, args.tile, c)
            for name, r in (("local disk", local), ("S3 (moto)", remote)):
                print(f"| {'dense' if dense else 'polynomial'} | {size}² | {name} | {r['wall']:.1f} | {r['mpx']:.2f} | "
                      f"{r['objects']} | {r['commit']:.2f} | {remote['wall'] / local['wall'] if r is remote else 1:.2f} |", flush=True)


if __name__ == "__main__":
    main()
