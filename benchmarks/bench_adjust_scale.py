"""Block adjustment at scale: seconds per Gauss-Newton iteration and peak memory, 100-1000 frames.

A synthetic block of ``strips x frames`` image frames, 32 parameters each, about 1,000 image
observations per frame (1,000,000 at 1,000 frames), solved by :func:`geocoder.adjust.solver.adjust`
(points eliminated first, sparse reduced normal equations).

The sensor model is :class:`Bicubic` below: ``x`` and ``y`` are tensor-product bicubic
polynomials (16 terms each, 32 parameters) of the frame's local ground coordinates -- the same
number of unknowns per frame as the seed's line scanner (8 orbit/time + 24 deviation
coefficients), but with analytic Jacobians.  :class:`geocoder.adjust.models.LineScannerModel`
takes ~0.05 s for the Jacobians of one frame with 1,000 points (implicit differentiation at the
solved time), i.e. ~50 s per iteration at 1,000 frames, which would measure the sensor geometry
more than the solver.

Layout: frames of 1,000 x 1,000 px over 10 x 10 km, centres 6 km apart along and across the
strips (40 % overlap both ways); ground points uniformly random over the block (each seen by ~2.8
frames); every 20th point is a control point (1 m a-priori sigma), the others are tie points
with only their height held (15 m; the 2-D model ignores height).  Image noise 0.3 px; the
start parameters are the truth plus ~2 px offsets and 0.2 % affine errors, so the solver needs
a few iterations.  Each size runs in a fresh subprocess; its peak resident memory is sampled
by a psutil thread every 20 ms (the whole process, data generation included).

Run:  python benchmarks/bench_adjust_scale.py            # 100, 200, 500, 1000 frames
      python benchmarks/bench_adjust_scale.py --quick    # 20, 50 frames
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

from geocoder.adjust.solver import AdjustOptions, Frame, Problem, adjust

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


def run_one(n_frames: int, iterations: int) -> dict:
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
    problem, truth = make_block(n_frames)
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = adjust(problem, AdjustOptions(max_iter=iterations, tol=1e-8, covariance=False))
    t_total = time.perf_counter() - t0
    stop.set()
    th.join()
    err = np.sqrt(np.mean([np.mean((np.asarray(p) - q)[[0, 16]] ** 2) for p, q in zip(res.params, truth)]))
    return {
        "frames": n_frames, "unknowns": 32 * n_frames, "points": int(problem.ground.shape[0]),
        "observations": int(problem.obs_frame.size), "iterations": res.iterations,
        "s_per_iteration": float(np.median(res.time_per_iteration)), "adjust_s": t_total, "build_s": t_build,
        "peak_gb": peak[0] / 1e9, "solver": res.solver, "sigma0": res.sigma0, "offset_error_px": float(err),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="20 and 50 frames only")
    ap.add_argument("--frames", type=int, nargs="*", help="block sizes (frames)")
    ap.add_argument("--iterations", type=int, default=3, help="Gauss-Newton iterations per size")
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)  # internal: one size, JSON on stdout
    a = ap.parse_args()
    if a.one:
        print(json.dumps(run_one(a.one, a.iterations)))
        return
    sizes = a.frames or ([20, 50] if a.quick else [100, 200, 500, 1000])
    print(f"{psutil.cpu_count()} CPUs, {psutil.virtual_memory().total / 1e9:.0f} GB RAM; "
          f"model: bicubic, 32 parameters per frame; median of {a.iterations} Gauss-Newton iterations\n")
    print("| frames | unknowns | observations | s/iteration | peak GB | growth (time ratio / size ratio) | solver | sigma0 |")
    print("|---:|---:|---:|---:|---:|---:|---|---:|")
    prev = None
    for n in sizes:
        out = subprocess.run([sys.executable, __file__, "--one", str(n), "--iterations", str(a.iterations)],
                             capture_output=True, text=True, check=True)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        growth = "-" if prev is None else (f"{r['s_per_iteration'] / prev['s_per_iteration']:.2f} / "
                                           f"{r['frames'] / prev['frames']:.1f}")
        print(f"| {r['frames']} | {r['unknowns']:,} | {r['observations']:,} | {r['s_per_iteration']:.2f} | "
              f"{r['peak_gb']:.2f} | {growth} | {r['solver']} | {r['sigma0']:.2f} |", flush=True)
        prev = r


if __name__ == "__main__":
    main()
