"""Mosaic at scale: an N x N block of small scenes end to end, time per stage and worker memory; a paper estimate for more.

The block is made as in ``bench_mosaic.py`` (:mod:`geocoder.simulate.block` over a crop of the
real Sentinel-2 image in ../shared/data: rotation, scale, a quadratic term, gain, offset and
noise per scene, 20 % overlap along the strips, 60 % sidelap) with control on every scene.
Printed: scenes, overlapping pairs, tie and ground points, seconds per stage (from the
mosaic's summary), wall time, the peak resident memory of each worker process (its
high-water mark, read from the kernel at the end), and the geometric error of the mosaic
against the truth (RMSE and max over every output pixel, output pixels). Then, per stage: the
Dask tasks run (counted by a scheduler plugin), the graphs submitted to the scheduler, and the
rounds of ``Job.run_tiles`` (a round: a set of tile tasks goes out, the client waits for all
of them); and the least-cost seam cut's seconds per pair (the cut is a loop on one node).

Every scene carries an approximate georeference (the north-up affine nearest its true mapping,
shifted by up to 4 px, as a navigation system gives it) unless ``--no-georeference``: then each scene
is searched for on the whole reference, which fails for scenes much smaller than the reference.

The estimate (``--estimate-scenes``, default 10,000; printed after a run, or alone from a run's
saved figures with ``--estimate FILE``): the same layout on an M x M grid. Pairs are counted
exactly from the measured neighbour offsets (a pair of grid offset ``(dr, dc)`` occurs
``(M - |dr|)(M - |dc|)`` times); tasks, tie points and the gathered table scale with the
scenes and pairs by the measured figures per scene and per pair; the reduced normal matrix has
a block of ``u x u`` (``u`` parameters per scene) per scene and two per tied pair; its solve is
the measured block adjustment scaled by the growth exponent of ``bench_adjust_scale.py``
(bicubic, 32 parameters per frame, run here in subprocesses with ``OPENBLAS_NUM_THREADS=1`` at
``--adjust-frames``); the seam cut is the measured seconds per pair and pass times the pairs.

Run:  python benchmarks/bench_mosaic_scale.py [--grid 10] [--size 192] [--workers 2] [--no-georeference]
                                              [--save FIGURES.json] [--estimate-scenes 10000] [--adjust-frames 100 300]
      python benchmarks/bench_mosaic_scale.py --estimate FIGURES.json      # the estimate alone
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import fields
from pathlib import Path

import numpy as np
import rasterio
from distributed import Client, LocalCluster
from distributed.diagnostics.plugin import SchedulerPlugin

import geocoder.mosaic.seams as seams_module
from geocoder.match.tiepoints import TiePoints
from geocoder.mosaic import load_models, mosaic
from geocoder.pipeline.job import Job
from geocoder.quality.accuracy import mosaic_errors
from geocoder.scene import write_geotiff
from geocoder.simulate.block import block_layout, render

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
S2 = DATA / "s2_arosics" / "ref_S2A_20160608T153121_T33UUU_sub.tif"


def _peak_rss_mib() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class _GraphCounter(SchedulerPlugin):
    """Graph submissions (``update_graph``) and tasks finished, with the time of each."""

    def __init__(self) -> None:
        self.graphs: list[float] = []
        self.done: list[float] = []

    def update_graph(self, scheduler, *, client, keys, tasks, annotations, priority, stimulus_id, **kwargs) -> None:
        self.graphs.append(time.time())

    def transition(self, key, start, finish, *args, stimulus_id, **kwargs) -> None:
        if start == "processing" and finish == "memory":
            self.done.append(time.time())


class _StageLog(logging.Handler):
    """When each stage of the mosaic began (its timer logs ``<stage> ...``)."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.starts: list[tuple[float, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        msg = record.getMessage()
        if msg.endswith(" ..."):
            self.starts.append((record.created, msg[:-4]))


_ROUNDS: list[tuple[float, int]] = []  # (time, tasks) of every Job.run_tiles call
_CUTS: list[float] = []  # seconds of every least-cost cut of one pair (seams.cut_pair)


def _count_rounds() -> None:
    """Count every :meth:`Job.run_tiles` call (a round: its tasks go out, the results come back)."""
    original = Job.run_tiles

    def counted(self, stage, tasks, phase=None):
        _ROUNDS.append((time.time(), len(tasks)))
        return original(self, stage, tasks, phase)

    Job.run_tiles = counted
    cut = seams_module.cut_pair

    def timed(*a, **kw):
        t = time.perf_counter()
        try:
            return cut(*a, **kw)
        finally:
            _CUTS.append(time.perf_counter() - t)

    seams_module.cut_pair = timed


def _per_stage(stages: list[str], starts: list[tuple[float, str]], times: list[float]) -> dict[str, int]:
    """How many of ``times`` fall into each top-level stage (from its first start to the next stage's)."""
    first: dict[str, float] = {}
    for t, name in starts:
        if name in stages and name not in first:
            first[name] = t
    edges = sorted((t, name) for name, t in first.items())
    out = {name: 0 for name in stages}
    for t in times:
        now = [name for start, name in edges if start <= t]
        if now:
            out[now[-1]] += 1
    return out


def _affine_fit(scene, size: int) -> rasterio.Affine:
    """The north-up affine scene pixel -> ortho pixel nearest the scene's true mapping (least squares).

    North-up, as a provider's georeference is: geocoder opens a scene with a rotated
    geotransform as not georeferenced. The scene's rotation (up to 3 degrees) is left to the
    coarse alignment.
    """
    ys, xs = np.mgrid[0:size:16, 0:size:16].astype(np.float64)
    ox, oy = scene.to_ortho(xs, ys)
    one = np.ones(xs.size)
    a, c = np.linalg.lstsq(np.column_stack([xs.ravel(), one]), ox.ravel(), rcond=None)[0]
    e, f = np.linalg.lstsq(np.column_stack([ys.ravel(), one]), oy.ravel(), rcond=None)[0]
    # rasterio's Affine maps pixel corners; the fit maps pixel centres
    return rasterio.Affine(a, 0.0, c - 0.5 * a + 0.5, 0.0, e, f - 0.5 * e + 0.5)


def measure(args) -> dict:
    """Run the block end to end; print its tables; return the figures the estimate needs."""
    n, size = args.grid, args.size
    work = Path(tempfile.mkdtemp(prefix="bench-mosaic-scale-"))
    with rasterio.open(S2) as src:
        full = src.read(1).astype(np.float32)
        t = src.transform
    scenes = block_layout(n, n, size=size, overlap=(0.2, 0.6), origin=(40.0, 40.0), seed=5)
    height = int(max(s.row0 for s in scenes) + 1.2 * size + 80)
    width = int(max(s.col0 for s in scenes) + 1.2 * size + 80)
    # the first crop (from the top, flush right) clear of the image's no-data wedge in the west
    c0 = full.shape[1] - width - 8
    r0 = next((r for r in range(0, full.shape[0] - height, 25) if c0 >= 0 and (full[r : r + height, c0 : c0 + width] > 0).all()), None)
    if r0 is None:
        raise SystemExit(f"a {n} x {n} block of {size} px scenes needs {height} x {width} px of valid image; use a smaller --size")
    ortho = full[r0 : r0 + height, c0 : c0 + width]
    transform = t * rasterio.Affine.translation(c0, r0)
    write_geotiff(work / "ortho.tif", ortho, transform=transform, crs="EPSG:32633")
    paths = []
    rng = np.random.default_rng(7)
    for k, s in enumerate(scenes):
        paths.append(work / f"scene{k:03d}.tif")
        georef = {}
        if not args.no_georeference:
            # an approximate georeference, as a navigation system or a provider gives it: the
            # north-up affine nearest the scene's true mapping, off by up to 4 ortho pixels
            a = _affine_fit(s, size) * rasterio.Affine.translation(*rng.uniform(-4, 4, 2))
            georef = {"transform": transform * a, "crs": "EPSG:32633"}
        write_geotiff(paths[-1], render(ortho, s, seed=k), **georef)
    with LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, dashboard_address=":0") as cl, Client(cl) as c:
        counter = _GraphCounter()
        cl.scheduler.add_plugin(counter)  # the LocalCluster's scheduler runs in this process
        stage_log = _StageLog()
        logger = logging.getLogger("geocoder")
        logger.addHandler(stage_log)
        logger.setLevel(logging.INFO)
        _count_rounds()
        t0 = time.perf_counter()
        ds = mosaic(paths, reference=work / "ortho.tif", out=work / "mosaic.zarr", tile=args.tile, client=c, show_progress=True)
        wall = time.perf_counter() - t0
        peaks = c.run(_peak_rss_mib)
    placed = [paths.index(Path(q)) for q in json.loads(ds.attrs["scenes"])]
    own, seam = mosaic_errors(ds, [scenes[k].to_ortho for k in placed], [(size, size)] * len(placed), transform)
    own = own[np.isfinite(own)]
    s = json.loads(ds.attrs["summary"])
    ties = sum(p["ties"] for p in s["pairs"])
    print(f"\nMosaic scale: {n} x {n} = {len(scenes)} scenes of {size}² px over a {height} x {width} Sentinel-2 crop, "
          f"tile {args.tile}, {args.workers} workers")
    print("| scenes | placed | pairs | tie points | ground points by rays | mosaic px | wall s | "
          + " | ".join(f"{k} s" for k in s["seconds"]) + " | worker peak MiB | RMSE px | max px | seam RMS px |")
    print("|" + "---:|" * (10 + len(s["seconds"])))
    print(f"| {len(scenes)} | {len(scenes) - len(s['left_out'])} | {len(s['pairs'])} | {ties} | {s['rays']} | "
          f"{s['shape'][0]} x {s['shape'][1]} | {wall:.1f} | " + " | ".join(f"{v:.1f}" for v in s["seconds"].values())
          + f" | {', '.join(f'{v:.0f}' for v in peaks.values())} | {np.sqrt(np.mean(own**2)):.3f} | {own.max():.3f} | "
          f"{np.sqrt(np.mean(seam**2)):.3f} |")
    for k, why in s["left_out"].items():
        print(f"left out: scene {k}: {why}")
    stages = list(s["seconds"])
    tasks = _per_stage(stages, stage_log.starts, counter.done)
    graphs = _per_stage(stages, stage_log.starts, counter.graphs)
    rounds = _per_stage(stages, stage_log.starts, [t for t, _ in _ROUNDS])
    print("\nPer stage: seconds, Dask tasks run, graphs submitted to the scheduler, rounds of run_tiles")
    print("| stage | s | tasks | graph submissions | run_tiles rounds |")
    print("|---|---:|---:|---:|---:|")
    for k in stages:
        print(f"| {k} | {s['seconds'][k]:.1f} | {tasks[k]} | {graphs[k]} | {rounds[k]} |")
    print(f"| total | {wall:.1f} | {len(counter.done)} | {len(counter.graphs)} | {len(_ROUNDS)} |")
    tied = [p for p in s["pairs"] if p["ties"] > 0]
    cut_pairs = len([p for p in tied if p["i"] not in map(int, s["left_out"]) and p["j"] not in map(int, s["left_out"])])
    if _CUTS:
        print(f"\nleast-cost seam cut (one node): {len(_CUTS)} cuts of {cut_pairs} pairs "
              f"({len(_CUTS) / max(cut_pairs, 1):.1f} passes), {1e3 * np.mean(_CUTS):.1f} ms per cut, {sum(_CUTS):.2f} s in all")
    params = [len(p) for _, p in load_models(ds)]
    return {
        "grid": n, "size": size, "scenes": len(scenes), "workers": args.workers, "tile": args.tile,
        # grid offsets (rows, cols) of every overlapping pair and of every pair that got tie points
        "pair_offsets": [[p["j"] // n - p["i"] // n, p["j"] % n - p["i"] % n] for p in s["pairs"]],
        "tied_offsets": [[p["j"] // n - p["i"] // n, p["j"] % n - p["i"] % n] for p in tied],
        "tie_points": ties, "control_points": int(sum(s["control_points"])),
        "ground_points": int(sum(int(v) for v in s["rays"].values())),
        "observations": int(sum(int(k) * int(v) for k, v in s["rays"].items())),
        "params_per_scene": int(np.max(params)), "mosaic_shape": list(s["shape"]),
        "seconds": s["seconds"], "wall": wall, "tasks": tasks, "graphs": graphs, "rounds": rounds,
        "worker_peak_mib": list(peaks.values()), "cut_seconds": float(np.mean(_CUTS)) if _CUTS else float("nan"),
        "cut_passes": len(_CUTS) / max(cut_pairs, 1),
    }


def _pairs_on_grid(offsets: list, n: int, m: int) -> float:
    """Pairs on an ``m x m`` grid of the same layout, from the grid offsets ``(dr, dc)`` of the pairs of the ``n x n`` block.

    An offset that occurs ``k`` times among the ``(n - |dr|)(n - |dc|)`` scene pairs it could
    join there joins the same fraction of its ``(m - |dr|)(m - |dc|)`` on the larger grid.
    """
    count: dict = {}
    for o in offsets:
        count[tuple(o)] = count.get(tuple(o), 0) + 1
    return float(sum(k * max(m - abs(dr), 0) * max(m - abs(dc), 0) / ((n - abs(dr)) * (n - abs(dc)))
                     for (dr, dc), k in count.items()))


def _adjust_growth(frames: list[int]) -> list[dict]:
    """``bench_adjust_scale.py`` (bicubic, 32 parameters per frame) at ``frames``, each in a subprocess, one BLAS thread."""
    script = Path(__file__).with_name("bench_adjust_scale.py")
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    out = []
    for f in frames:
        r = subprocess.run([sys.executable, str(script), "--one", str(f), "--iterations", "3", "--model", "bicubic"],
                           capture_output=True, text=True, check=True, env=env)
        out.append(json.loads(r.stdout.strip().splitlines()[-1]))
    return out


def estimate(m: dict, target: int, adjust_runs: list[dict]) -> None:
    """Print the paper estimate for ``target`` scenes from the measured figures ``m``."""
    n0, side = m["scenes"], int(round(np.sqrt(target)))
    n1 = side * side
    pairs0, pairs1 = len(m["pair_offsets"]), round(_pairs_on_grid(m["pair_offsets"], m["grid"], side))
    tied0, tied1 = len(m["tied_offsets"]), round(_pairs_on_grid(m["tied_offsets"], m["grid"], side))
    ties_per_pair = m["tie_points"] / max(tied0, 1)
    ctrl_per_scene = m["control_points"] / n0
    ties1 = ties_per_pair * tied1
    ctrl1 = ctrl_per_scene * n1
    tp_bytes = sum(8 if f.name != "inlier" else 1 for f in fields(TiePoints))
    # the gathered observations of the adjustment: frame, point (int64), xy (2 float64), 2x2 weight;
    # a ground point: position, prior (3 float64 each) and its 3x3 weight
    obs_bytes, point_bytes = 8 + 8 + 16 + 32, 24 + 24 + 72
    obs_per_tie = m["observations"] / max(m["ground_points"], 1)
    points1 = ties1 + ctrl1
    u = m["params_per_scene"]
    blocks1 = n1 + 2 * tied1  # diagonal, and both triangles of every tied pair
    # the tasks per stage: per scene (ingest, interest points, control points, mosaic and seam
    # tiles scale with the area, i.e. the scenes) and per pair (tie points)
    per = {k: ("pairs" if k == "tie points" else "scenes") for k in m["tasks"]}
    rows = []
    for k, v in m["tasks"].items():
        scale = (pairs1 / max(pairs0, 1)) if per[k] == "pairs" else (n1 / n0)
        rows.append((k, v, v * scale, m["rounds"][k], m["seconds"][k], m["seconds"][k] * scale))
    # the solve: the measured block adjustment, grown as the bicubic block grows between the sizes run
    if len(adjust_runs) >= 2:
        f = np.log([r["frames"] for r in adjust_runs])
        t = np.log([r["s_per_iteration"] for r in adjust_runs])
        b = float(np.polyfit(f, t, 1)[0])
    else:
        b = 1.0
    adj0 = m["seconds"].get("block adjustment", float("nan"))
    big = adjust_runs[-1] if adjust_runs else None
    print(f"\nPaper estimate: {side} x {side} = {n1:,} scenes of {m['size']}² px, the measured {m['grid']} x {m['grid']} "
          f"block's layout ({m['workers']} workers measured)")
    print("| quantity | measured (" + f"{n0} scenes) | estimate ({n1:,} scenes) | how |")
    print("|---|---:|---:|---|")
    print(f"| overlapping pairs | {pairs0:,} | {pairs1:,} | {len(set(map(tuple, m['pair_offsets'])))} neighbour offsets "
          f"x their count on the grid ({pairs1 / n1:.2f} pairs per scene) |")
    print(f"| pairs with tie points | {tied0:,} | {tied1:,} | as above |")
    print(f"| tie points | {m['tie_points']:,} | {ties1:,.0f} | {ties_per_pair:.1f} per tied pair |")
    print(f"| control points | {m['control_points']:,} | {ctrl1:,.0f} | {ctrl_per_scene:.1f} per scene |")
    for k, v0, v1, r, s0, s1 in rows:
        print(f"| {k}: tasks / rounds / s | {v0:,} / {r} / {s0:.1f} | {v1:,.0f} / {r} / {s1:,.0f} | per {per[k][:-1]}; "
              f"rounds do not grow |")
    print(f"| tasks in all | {sum(r[1] for r in rows):,} | {sum(r[2] for r in rows):,.0f} | |")
    print(f"| gathered tie-point table (TiePoints, {tp_bytes} B/point) | {m['tie_points'] * tp_bytes / 1e6:.2f} MB | "
          f"{ties1 * tp_bytes / 1e6:.1f} MB | all passes' points are gathered per pair, then thinned to the inliers |")
    print(f"| adjustment's observations ({obs_bytes} B) and ground points ({point_bytes} B) | "
          f"{(m['observations'] * obs_bytes + m['ground_points'] * point_bytes) / 1e6:.2f} MB | "
          f"{(points1 * obs_per_tie * obs_bytes + points1 * point_bytes) / 1e6:.1f} MB | "
          f"{obs_per_tie:.2f} rays per ground point |")
    print(f"| reduced normal matrix: {u} x {u} blocks, nonzero | {n0 + 2 * tied0:,} | {blocks1:,} | one per scene, two per tied pair |")
    print(f"| reduced normal matrix: memory (float64) | {(n0 + 2 * tied0) * u * u * 8 / 1e6:.2f} MB | "
          f"{blocks1 * u * u * 8 / 1e6:.1f} MB | dense would be {(n1 * u) ** 2 * 8 / 1e9:,.0f} GB |")
    print(f"| block adjustment (solve) s | {adj0:.1f} | {adj0 * (n1 / n0) ** b:,.0f} | x (scenes ratio)^{b:.2f}, the growth of "
          f"bench_adjust_scale.py between {', '.join(str(r['frames']) for r in adjust_runs)} frames |")
    if big is not None:
        print(f"| bench_adjust_scale s/iteration (32 par./frame) | {big['s_per_iteration']:.2f} at {big['frames']} frames | "
              f"{big['s_per_iteration'] * (n1 / big['frames']) ** b:,.1f} | an upper bound per iteration ({u} par. here) |")
    cut1 = m["cut_seconds"] * m["cut_passes"] * tied1
    print(f"| least-cost seam cut (one node) s | {m['cut_seconds'] * m['cut_passes'] * tied0:.1f} | {cut1:,.0f} | "
          f"{1e3 * m['cut_seconds']:.1f} ms per cut x {m['cut_passes']:.1f} passes x pairs |")
    h, w = m["mosaic_shape"]
    print(f"| mosaic | {h} x {w} px | ~{h * side / m['grid']:,.0f} x {w * side / m['grid']:,.0f} px | the side grows with the grid |")
    if adjust_runs:
        print("\nbench_adjust_scale.py (bicubic, OPENBLAS_NUM_THREADS=1): "
              + "; ".join(f"{r['frames']} frames {r['s_per_iteration']:.2f} s/iteration, {r['peak_gb']:.2f} GB peak"
                          for r in adjust_runs))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grid", type=int, default=10, help="scenes per side")
    ap.add_argument("--size", type=int, default=192, help="scene side (px)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--tile", type=int, default=256)
    ap.add_argument("--no-georeference", action="store_true",
                    help="scenes without any georeference (each is searched for on the whole reference)")
    ap.add_argument("--save", type=Path, help="write the measured figures (JSON) for --estimate")
    ap.add_argument("--estimate", type=Path, help="print the estimate alone, from a run's --save file "
                    "(bench_adjust_scale.py's figures are kept in it)")
    ap.add_argument("--estimate-scenes", type=int, default=10_000, help="scenes of the estimate (0: none)")
    ap.add_argument("--adjust-frames", type=int, nargs="*", default=[100, 300],
                    help="bench_adjust_scale.py sizes that give the solve's growth (none: linear)")
    args = ap.parse_args()
    if args.estimate is not None:
        measured = json.loads(args.estimate.read_text())
    else:
        measured = measure(args)
    if args.estimate_scenes:
        runs = measured.get("adjust_runs")
        if not runs or [r["frames"] for r in runs] != args.adjust_frames:
            runs = measured["adjust_runs"] = _adjust_growth(args.adjust_frames)
        estimate(measured, args.estimate_scenes, runs)
    path = args.save or args.estimate
    if path is not None:  # with the solver's figures, if measured: --estimate FILE then prints at once
        path.write_text(json.dumps(measured, indent=1))


if __name__ == "__main__":
    main()
