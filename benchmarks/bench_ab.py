"""Interleaved A/B of dense-matching options on one local cluster: wall time, task time per stage, accuracy.

On a shared, noisy machine two benchmark runs minutes apart can differ by 10-20 % in stages
that neither configuration touches. Here the configurations take turns on ONE warm local
cluster (geocoder's own :func:`geocoder.runtime.local_cluster`), ``--repeat`` rounds of one
run each, on the pair of ``bench_speed.py`` (a 2048² Sentinel-2 crop warped by an
airborne-like field, known truth). Per run: wall time of ``register``, the workers' task
seconds in all (Dask's task stream) and in the dense stage's two task kinds (the lattice's
region growing and the every-pixel pass), RMSE of the matched pixels against the truth and
their share of the overlap. A last table gives each configuration's mean.

Configurations are named ``key=value`` lists, separated by ``,``, of fields of
:class:`geocoder.pipeline.dense.DenseOptions` or scalar fields of
:class:`geocoder.pipeline.register.RegisterOptions` (``passes=1``); ``default`` is today's default.

Usage::

    python benchmarks/bench_ab.py "row_step=1,lattice_tol=0.01" default [--repeat 3] [--size 2048] [--workers 2]
"""

from __future__ import annotations

import argparse
import re
import tempfile
import time
from collections import Counter
from dataclasses import fields
from pathlib import Path

import numpy as np
from bench_speed import make_case, overlap_mask  # the script's directory is on sys.path

#: Task-name prefixes of the dense stage's tasks (``grow-<tile>-r<round>-<token>``, ``densify-...``).
KINDS = {"growth": "grow-", "every pixel": "densify-", "correspondence": "correspond"}


def parse_options(spec: str):
    """``"default"`` or ``"name=value,name=value"`` -> RegisterOptions; a name is a field of
    :class:`geocoder.pipeline.dense.DenseOptions` or a scalar field of
    :class:`geocoder.pipeline.register.RegisterOptions` (values parsed as their field's type)."""
    from dataclasses import replace

    from geocoder.pipeline.dense import DenseOptions
    from geocoder.pipeline.register import RegisterOptions

    if spec == "default":
        return RegisterOptions()
    parse = {"int": int, "float": float, "str": str}
    dense_types = {f.name: str(f.type) for f in fields(DenseOptions)}
    register_types = {f.name: str(f.type) for f in fields(RegisterOptions) if str(f.type) in parse}
    dense, register = {}, {}
    for item in spec.split(","):
        name, _, value = item.partition("=")
        if name in dense_types:
            dense[name] = parse.get(dense_types[name], float)(value)
        elif name in register_types:
            register[name] = parse[register_types[name]](value)
        else:
            raise SystemExit(f"{spec!r}: neither DenseOptions nor RegisterOptions has a field {name!r}")
    return replace(RegisterOptions(matching=DenseOptions(**dense)), **register)


def task_seconds(stream: list[dict]) -> Counter:
    """Compute seconds per task kind (``all`` and :data:`KINDS`) from a Dask task stream."""
    out: Counter = Counter()
    for t in stream:
        key = t["key"][0] if isinstance(t["key"], tuple) else str(t["key"])
        busy = sum(s["stop"] - s["start"] for s in t["startstops"] if s["action"] == "compute")
        out["all"] += busy
        for kind, prefix in KINDS.items():
            if re.match(prefix, key):
                out[kind] += busy
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("configs", nargs="+", help='"default" or "field=value,..." of DenseOptions or RegisterOptions')
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()

    from distributed import Client, get_task_stream

    from geocoder import Status, register
    from geocoder.runtime import local_cluster

    options = {c: parse_options(c) for c in args.configs}
    rows: list[tuple] = []
    with tempfile.TemporaryDirectory(prefix="bench-ab-") as tmp:
        work = Path(tmp)
        case = make_case(args.size, work)
        pair, overlap = case["pair"], overlap_mask(case["pair"])
        with local_cluster(args.workers) as cluster, Client(cluster) as client:
            # numba loads or compiles its kernels in the workers
            register(work / "warm-base.tif", work / "warm-dist.tif", client=client)
            for rep in range(args.repeat):
                for name, opts in options.items():
                    with get_task_stream(client) as ts:
                        t0 = time.perf_counter()
                        ds = register(case["base"], case["dist"], client=client, out=work / "out.zarr",
                                      overwrite=True, options=opts, show_progress=False)
                        wall = time.perf_counter() - t0
                    busy = task_seconds(ts.data)
                    matched = ds.status.values == Status.MATCHED
                    err = np.hypot(ds.dx.values - pair.dx, ds.dy.values - pair.dy)[matched]
                    rows.append((rep + 1, name, wall, busy["all"], busy["correspondence"], busy["growth"], busy["every pixel"],
                                 float(np.sqrt(np.mean(err**2))), float((matched & overlap).sum() / overlap.sum())))
                    print(f"round {rep + 1}: {name}: {wall:.2f} s", flush=True)
    head = "| wall s | task s | correspondence tasks s | growth tasks s | every-pixel tasks s | RMSE matched px | matched share of overlap |"
    print(f"\n{args.size}² pair, {args.workers} workers, configurations alternated\n")
    print("| round | configuration " + head)
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    for rep, name, *v in rows:
        print(f"| {rep} | {name} | {v[0]:.2f} | {v[1]:.2f} | {v[2]:.2f} | {v[3]:.2f} | {v[4]:.2f} | {v[5]:.4f} | {100 * v[6]:.2f} % |")
    print("\n| configuration " + head)
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for name in options:
        v = np.array([r[2:] for r in rows if r[1] == name])
        m = v.mean(axis=0)
        print(f"| {name} | {m[0]:.2f} | {m[1]:.2f} | {m[2]:.2f} | {m[3]:.2f} | {m[4]:.2f} | {m[5]:.4f} | {100 * m[6]:.2f} % |")


if __name__ == "__main__":
    main()
