"""Block adjustment at scale: seconds per Gauss-Newton iteration and peak memory, 100-1000 frames.

A synthetic block of ``strips x frames`` image frames, 32 parameters each, about 1,000 image
observations per frame (~1,000,000 at 1,000 frames), solved by :func:`geocoder.adjust.solver.adjust`
(points eliminated first, sparse reduced normal equations), with two sensor models:

``bicubic``
    :class:`Bicubic` below: ``x`` and ``y`` are tensor-product bicubic polynomials (16 terms
    each, 32 parameters) of the frame's local ground coordinates.  Frames of 1,000 x 1,000 px
    over 10 x 10 km, centres 6 km apart along and across the strips (40 % overlap both ways);
    ground points uniformly random over the block (each seen by ~2.8 frames).  The start
    parameters are the truth plus ~2 px offsets and 0.2 % affine errors.
``linescanner``
    The seed's parametric line scanner (:class:`geocoder.adjust.models.LineScannerModel`, all
    8 orbit/time + 24 deviation parameters free, exact Jacobians): LANDSAT-MSS-like frames of
    468 x 648 px (79 m lines, 37 km swath) from :func:`geocoder.simulate.points.block_of_strips`
    (60 % sidelap, 15 % overlap, random cubic position/attitude deviations of ~15 m and
    5e-5 rad), over rolling terrain.  Each frame gets ~340 random ground points inside it, each
    observed in every frame that sees it (~3 frames).  The adjustment starts from the nominal
    orbit (deviations zero, ~1 px off) with weak priors: 200 m / 2e-3 rad over the frame's half
    duration for the deviation coefficients (as :mod:`geocoder.simulate.adjust_experiments`) and ~1 px
    (100 ``param_steps``) for the orbit and time parameters.

Both: every 20th point is a control point (1 m a-priori sigma), the others are tie points with
only their height held (15 m); image noise 0.3 px; tie points start 20 m off.  Each size runs in
a fresh subprocess; its peak resident memory is sampled by a psutil thread every 20 ms (the whole
process, data generation included).  ``s/iteration`` is the median wall time of a Gauss-Newton
step (solve, back-substitution, new residuals, Jacobians, reduced normal equations).
``--block-size`` sets the observations per chunk of the streamed assembly
(:mod:`geocoder.adjust.normals`); ``--block-size 0`` assembles everything at once and keeps the
Jacobians (faster, memory proportional to the observations); ``--keep-jacobians 0`` evaluates the
parameter Jacobians again for the back-substitution instead of keeping them (memory bounded by
the block size, one more Jacobian evaluation per iteration).

On a shared machine set ``OPENBLAS_NUM_THREADS=1``: a multi-threaded BLAS whose threads wait for
a busy core can be several times slower than one thread.

Run:  python benchmarks/bench_adjust_scale.py                  # both models, 100, 300, 1000 frames
      python benchmarks/bench_adjust_scale.py --quick          # both models, 20 and 50 frames
      python benchmarks/bench_adjust_scale.py --models linescanner --frames 100
      python benchmarks/bench_adjust_scale.py --block-size 0              # one chunk
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time

import numpy as np
import psutil

from geocoder.adjust.models import LineScannerModel
from geocoder.adjust.normals import DEFAULT_BLOCK_SIZE
from geocoder.adjust.solver import AdjustOptions, Frame, Problem, adjust
from geocoder.simulate.points import block_of_strips
from geocoder.simulate.satellite import ecef_to_geodetic

SIZE = 10_000.0  # frame footprint (m)
PIXELS = 1000.0  # frame size (px)
SPACING = 6_000.0  # distance between frame centres (m)


class Bicubic:
    """``x = sum_ij a_ij u^i v^j``, ``y = sum_ij b_ij u^i v^j`` (i, j = 0..3), ``(u, v)`` the
    ground east/north relative to the frame centre over half the footprint; height ignored."""

    n_params = 32

    def __init__(self, centre: np.ndarray) -> None:
        self.centre = np.asarray(centre, dtype=np.float64)
        self.scale = SIZE / 2

    def _uv(self, ground: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (ground[:, 0] - self.centre[0]) / self.scale, (ground[:, 1] - self.centre[1]) / self.scale

    @staticmethod
    def _powers(u: np.ndarray) -> np.ndarray:
        return np.stack([np.ones_like(u), u, u * u, u * u * u], axis=1)  # (m, 4)

    @staticmethod
    def _dpowers(u: np.ndarray) -> np.ndarray:
        return np.stack([np.zeros_like(u), np.ones_like(u), 2 * u, 3 * u * u], axis=1)

    def project(self, params: np.ndarray, ground: np.ndarray) -> np.ndarray:
        u, v = self._uv(ground)
        mono = (self._powers(u)[:, :, None] * self._powers(v)[:, None, :]).reshape(-1, 16)
        return mono @ params.reshape(2, 16).T

    def jacobians(self, params: np.ndarray, ground: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u, v = self._uv(ground)
        pu, pv, du, dv = self._powers(u), self._powers(v), self._dpowers(u), self._dpowers(v)
        mono = (pu[:, :, None] * pv[:, None, :]).reshape(-1, 16)
        m = mono.shape[0]
        jp = np.zeros((m, 2, 32))
        jp[:, 0, :16] = mono
        jp[:, 1, 16:] = mono
        p = params.reshape(2, 16)
        d_u = (du[:, :, None] * pv[:, None, :]).reshape(-1, 16) @ p.T / self.scale  # (m, 2)
        d_v = (pu[:, :, None] * dv[:, None, :]).reshape(-1, 16) @ p.T / self.scale
        jg = np.stack([d_u, d_v, np.zeros_like(d_u)], axis=2)  # (m, 2, 3)
        return jp, jg

    def initial_params(self) -> np.ndarray:
        return np.zeros(32)


def make_block(n_frames: int, obs_per_frame: int = 1000, seed: int = 0) -> tuple[Problem, list[np.ndarray]]:
    """The problem (start values perturbed) and the true parameters of every frame."""
    rng = np.random.default_rng(seed)
    strips = max(1, int(round(np.sqrt(n_frames / 1.6))))
    per_strip = int(np.ceil(n_frames / strips))
    centres = np.array([(s * SPACING, f * SPACING) for s in range(strips) for f in range(per_strip)])[:n_frames]
    lo, hi = centres.min(0) - SIZE / 2, centres.max(0) + SIZE / 2
    # uniform density so that a frame (SIZE^2) sees obs_per_frame points
    n_points = int(round(obs_per_frame / SIZE**2 * np.prod(hi - lo)))
    xyz = np.column_stack([rng.uniform(lo[0], hi[0], n_points), rng.uniform(lo[1], hi[1], n_points),
                           rng.uniform(200.0, 600.0, n_points)])
    models, truth, start = [], [], []
    k = 16
    for c in centres:
        a = np.zeros((2, 4, 4))
        a[0, 0, 0], a[1, 0, 0] = PIXELS / 2, PIXELS / 2
        a[0, 1, 0], a[1, 0, 1] = PIXELS / 2, -PIXELS / 2  # x east, y south
        a[:, 2:, :] += rng.normal(0, 1.0, (2, 2, 4))  # a few pixels of higher-order distortion
        a[:, :, 2:] += rng.normal(0, 1.0, (2, 4, 2))
        p = a.reshape(32)
        q = p.copy()
        q[[0, k]] += rng.normal(0, 2.0, 2)  # offsets
        q[[1, 4, k + 1, k + 4]] += rng.normal(0, 1.0, 4)  # 0.2 % affine
        models.append(Bicubic(c))
        truth.append(p)
        start.append(q)
    # observations: every point in every frame whose footprint contains it
    fr, pt, xy = [], [], []
    for f, (c, mdl, p) in enumerate(zip(centres, models, truth)):
        inside = np.flatnonzero(np.all(np.abs(xyz[:, :2] - c) < SIZE / 2, axis=1))
        fr.append(np.full(inside.size, f))
        pt.append(inside)
        xy.append(mdl.project(p, xyz[inside]) + rng.normal(0, 0.3, (inside.size, 2)))
    obs_frame, obs_point, obs_xy = np.concatenate(fr), np.concatenate(pt), np.concatenate(xy)
    control = np.zeros(n_points, dtype=bool)
    control[::20] = True
    weight = np.zeros((n_points, 3, 3))
    weight[control] = np.eye(3) / 1.0**2
    weight[~control, 2, 2] = 1 / 15.0**2
    prior = xyz + np.where(control[:, None], rng.normal(0, 1.0, xyz.shape), 0.0)
    approx = xyz + rng.normal(0, 20.0, xyz.shape)  # tie points start 20 m off
    approx[control] = prior[control]
    problem = Problem(
        frames=[Frame(model=m, params=q) for m, q in zip(models, start)],
        ground=approx, ground_prior=prior, ground_weight=weight,
        obs_frame=obs_frame, obs_point=obs_point, obs_xy=obs_xy,
        obs_weight=np.broadcast_to(np.eye(2) / 0.3**2, (obs_frame.size, 2, 2)).copy(),
    )
    return problem, truth


def _terrain(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """Rolling terrain, 200-600 m (radians in, metres out)."""
    la, lo = np.rad2deg(lat), np.rad2deg(lon)
    return 400.0 + 120.0 * np.sin(la * 17.0) * np.cos(lo * 13.0) + 80.0 * np.sin(lo * 29.0 + 1.0)


def make_linescanner_block(n_frames: int, obs_per_frame: int = 1000, seed: int = 0) -> tuple[Problem, list[np.ndarray]]:
    """A block of line-scanner frames: the problem (nominal start) and the true 32-vectors."""
    rng = np.random.default_rng(seed)
    strips = max(1, round(float(np.sqrt(n_frames / 2.5))))
    per_strip = int(np.ceil(n_frames / strips))
    rows, cols, swath = 468, 648, 37e3
    truths = block_of_strips(strips=strips, frames=per_strip, seed=seed, rows=rows, cols=cols, swath=swath)
    idx = [(s, f) for s in range(strips) for f in range(per_strip)][:n_frames]
    truths = truths[: len(idx)]
    number = {sf: k for k, sf in enumerate(idx)}
    # each frame owns random points inside it, each seen by ~2.6 frames on average (edges included)
    per = max(1, round(obs_per_frame / 2.6))
    owned = []
    for sc in truths:
        r, c = rng.uniform(2, rows - 3, per), rng.uniform(2, cols - 3, per)
        owned.append(np.stack(sc.image_to_ground(r, c, terrain=_terrain), axis=-1))
    start = np.cumsum([0] + [len(o) for o in owned])
    xyz = np.concatenate(owned)
    # observations: the points of the 3 x 3 neighbouring frames that fall inside each frame
    fr, pt, xy = [], [], []
    for k, (s, f) in enumerate(idx):
        cand = [number[(s + ds, f + df)] for ds in (-1, 0, 1) for df in (-1, 0, 1) if (s + ds, f + df) in number]
        ids = np.concatenate([np.arange(start[j], start[j + 1]) for j in cand])
        r, c = truths[k].ground_to_image(xyz[ids, 0], xyz[ids, 1], xyz[ids, 2])
        inside = np.isfinite(r) & (r >= 0) & (r <= rows - 1) & (c >= 0) & (c <= cols - 1)
        fr.append(np.full(inside.sum(), k))
        pt.append(ids[inside])
        xy.append(np.stack([c[inside], r[inside]], axis=-1) + rng.normal(0, 0.3, (inside.sum(), 2)))
    obs_frame, obs_point, obs_xy = np.concatenate(fr), np.concatenate(pt), np.concatenate(xy)
    n_points = xyz.shape[0]
    lat, lon, _ = ecef_to_geodetic(xyz[:, 0], xyz[:, 1], xyz[:, 2])
    up = np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], axis=-1)
    control = np.zeros(n_points, dtype=bool)
    control[::20] = True
    weight = up[:, :, None] * up[:, None, :] / 15.0**2
    weight[control] = np.eye(3) / 1.0**2
    prior = xyz + np.where(control[:, None], rng.normal(0, 1.0, xyz.shape), 0.0)
    approx = xyz + rng.normal(0, 20.0, xyz.shape)
    approx[control] = prior[control]
    frames = []
    for sc in truths:
        template = sc.replace(deviations=np.zeros((6, 4)))
        model = LineScannerModel(template)
        t = template.time(np.array([0.0, rows - 1.0]), np.array([0.0, cols - 1.0]))
        half = float(np.max(np.abs(t)))
        sig_dev = np.repeat([200.0, 2e-3], 3)[:, None] / half ** np.arange(4)[None, :]
        sigma = np.concatenate([100.0 * model.param_steps[:8], sig_dev.ravel()])
        frames.append(Frame(model=model, params=model.initial_params(), prior_weight=np.diag(1.0 / sigma**2)))
    problem = Problem(
        frames=frames, ground=approx, ground_prior=prior, ground_weight=weight,
        obs_frame=obs_frame, obs_point=obs_point, obs_xy=obs_xy,
        obs_weight=np.broadcast_to(np.eye(2) / 0.3**2, (obs_frame.size, 2, 2)).copy(),
    )
    return problem, [sc.parameters() for sc in truths]


def run_one(n_frames: int, iterations: int, model: str = "bicubic", block_size: int | None = DEFAULT_BLOCK_SIZE,
            keep_jacobians: int | None = None) -> dict:
    proc = psutil.Process()
    peak = [proc.memory_info().rss]
    stop = threading.Event()

    def sample() -> None:
        while not stop.is_set():
            peak[0] = max(peak[0], proc.memory_info().rss)
            time.sleep(0.02)

    th = threading.Thread(target=sample, daemon=True)
    th.start()
    t0 = time.perf_counter()
    problem, truth = make_block(n_frames) if model == "bicubic" else make_linescanner_block(n_frames)
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    keep = {} if keep_jacobians is None else {"keep_jacobians": keep_jacobians}
    res = adjust(problem, AdjustOptions(max_iter=iterations, tol=1e-8, covariance=False, block_size=block_size, **keep))
    t_total = time.perf_counter() - t0
    stop.set()
    th.join()
    if model == "bicubic":
        err = np.sqrt(np.mean([np.mean((np.asarray(p) - q)[[0, 16]] ** 2) for p, q in zip(res.params, truth)]))
    else:  # ground error of the tie points (m) against the truth
        tie = np.all(problem.ground_weight[:, :2, :2] < 1.0, axis=(1, 2)) & res.point_valid
        truth_xyz = problem.ground_prior  # ties: prior = truth (only the height is weighted)
        err = float(np.sqrt(np.mean(np.sum((res.ground - truth_xyz)[tie] ** 2, axis=1))))
    return {
        "model": model, "frames": n_frames, "unknowns": 32 * n_frames, "points": int(problem.ground.shape[0]),
        "observations": int(problem.obs_frame.size), "iterations": res.iterations,
        "s_per_iteration": float(np.median(res.time_per_iteration)), "adjust_s": t_total, "build_s": t_build,
        "peak_gb": peak[0] / 1e9, "solver": res.solver, "block_size": block_size, "sigma0": res.sigma0, "offset_error_px": float(err),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="20 and 50 frames only")
    ap.add_argument("--models", nargs="*", default=["bicubic", "linescanner"], choices=["bicubic", "linescanner"])
    ap.add_argument("--frames", type=int, nargs="*", help="block sizes (frames)")
    ap.add_argument("--iterations", type=int, default=3, help="Gauss-Newton iterations per size")
    ap.add_argument("--block-size", type=int, default=DEFAULT_BLOCK_SIZE,
                    help=f"observations per chunk of the streamed assembly (default {DEFAULT_BLOCK_SIZE}; 0 = one chunk)")
    ap.add_argument("--keep-jacobians", type=int, default=None,
                    help="bytes of parameter Jacobians kept between assembly and back-substitution "
                         "(default: the library's; 0 = always evaluate again, memory bounded by the block size)")
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)  # internal: one size, JSON on stdout
    ap.add_argument("--model", default="bicubic", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.one:
        print(json.dumps(run_one(a.one, a.iterations, a.model, a.block_size or None, a.keep_jacobians)))
        return
    sizes = a.frames or ([20, 50] if a.quick else [100, 300, 1000])
    print(f"{psutil.cpu_count()} CPUs, {psutil.virtual_memory().total / 1e9:.0f} GB RAM; 32 parameters per frame; "
          f"median of {a.iterations} Gauss-Newton iterations; block size {a.block_size or 'all'} observations\n")
    print("| model | frames | unknowns | observations | s/iteration | iterations | peak GB | growth (time ratio / size ratio) "
          "| solver | sigma0 | error |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|")
    for model in a.models:
        prev = None
        for n in sizes:
            out = subprocess.run([sys.executable, __file__, "--one", str(n), "--iterations", str(a.iterations),
                                  "--model", model, "--block-size", str(a.block_size)]
                                 + ([] if a.keep_jacobians is None else ["--keep-jacobians", str(a.keep_jacobians)]),
                                 capture_output=True, text=True, check=True)
            r = json.loads(out.stdout.strip().splitlines()[-1])
            growth = "-" if prev is None else (f"{r['s_per_iteration'] / prev['s_per_iteration']:.2f} / "
                                               f"{r['frames'] / prev['frames']:.1f}")
            unit = "px" if model == "bicubic" else "m"
            print(f"| {model} | {r['frames']} | {r['unknowns']:,} | {r['observations']:,} | {r['s_per_iteration']:.2f} | "
                  f"{r['iterations']} | {r['peak_gb']:.2f} | {growth} | {r['solver']} | {r['sigma0']:.2f} | "
                  f"{r['offset_error_px']:.2f} {unit} |", flush=True)
            prev = r
    print("\nerror: bicubic, RMS of the frames' offset parameters against the truth (px); linescanner, RMS "
          "3-D error of the adjusted tie points (m)")


if __name__ == "__main__":
    main()
