"""``geocoder adjust``: files in, adjusted parameters, ground points, residuals and a report out."""

from __future__ import annotations

import csv
import io
import json
import os

import numpy as np

from ..errors import InputError
from ..outputs import check_output, commit_output, write_marker
from ..storage import remove, temporary_sibling
from .block import build_problem, check_errors
from .driver import adjust
from .io import read_frames, read_observations, read_points, write_frames, write_points, write_text
from .problem import AdjustOptions


def residual_svg(path: str, xy: np.ndarray, res: np.ndarray, active: np.ndarray, *, width: int = 600) -> None:
    """Residual vectors of one frame as an SVG (arrows exaggerated to 5 % of the frame)."""
    if xy.size == 0:
        return
    lo, hi = xy.min(0), xy.max(0)
    span = max(float((hi - lo).max()), 1.0)
    s = (width - 40) / span
    big = float(np.nanmax(np.hypot(*res.T))) or 1.0
    k = 0.05 * span / big
    lines = []
    for (x, y), (dx, dy), a in zip(xy, res, active):
        x0, y0 = 20 + (x - lo[0]) * s, 20 + (y - lo[1]) * s
        colour = "#1f77b4" if a else "#d62728"
        lines.append(f'<line x1="{x0:.1f}" y1="{y0:.1f}" x2="{x0 + dx * k * s:.1f}" y2="{y0 + dy * k * s:.1f}" '
                     f'stroke="{colour}" stroke-width="1.2"/><circle cx="{x0:.1f}" cy="{y0:.1f}" r="1.5" fill="{colour}"/>')
    height = int(40 + (hi[1] - lo[1]) * s)
    write_text(path, f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}">'
               f'<text x="20" y="14" font-size="11">residuals x{k:.0f} (largest {big:.2f} px); red = rejected</text>'
               + "".join(lines) + "</svg>")


def adjust_files(frames_path: str, points_path: str, obs_path: str, out: str, *, robust: bool = False,
                 snooping: bool = False, tie_height_sigma: float | None = 15.0, client=None, scheduler: str | None = None,
                 overwrite: bool = False) -> dict:
    """Run a block adjustment from files and write its results into the directory ``out``.

    ``out`` receives ``frames.json``, ``points.csv``, ``residuals.csv``, ``report.md`` and
    ``residuals_frame<k>.svg``. Points with role ``check`` are withheld and measured through the adjusted models. The
    adjustment is gathered on one node: this process, or with ``client`` / ``scheduler`` one
    task on a worker of that cluster (the files must be on a filesystem the worker sees).

    ``out`` is written whole: into a hidden sibling, renamed into place when complete; a
    failure before that (an error, a full disk) leaves an earlier ``out`` as it was.

    Parameters
    ----------
    frames_path : str
        Frames JSON: the sensor model and start parameters of every frame.
    points_path : str
        Ground points CSV (``id,role,X,Y,Z,sigma_X,sigma_Y,sigma_Z``); role ``control``,
        ``tie`` or ``check``.
    obs_path : str
        Image observations CSV (``frame,point,x,y,w_xx,w_xy,w_yy``).
    out : str
        Output directory.
    robust : bool
        Robust re-weighting (eq 20b, then eq 22b) of the image observations.
    snooping : bool
        Data snooping with redundancy numbers after the (robust) adjustment.
    tie_height_sigma : float or None
        Prior standard deviation (m) that holds the ellipsoidal height of every tie point to
        the value in ``points_path`` (its position is otherwise free). None: tie points are
        weighted by their ``sigma_*`` columns like the other points.
    client : distributed.Client, optional
        Run the adjustment as one task on this cluster.
    scheduler : str, optional
        Address of a Dask scheduler (or a ``cluster.json``) to run the task on, when no
        ``client`` is given.
    overwrite : bool
        Replace an existing ``out`` if geocoder wrote it (an empty directory is always
        fine); anything else is refused, as is an ``out`` equal to or containing an input or
        the working directory.

    Returns
    -------
    dict
        The summary the CLI prints: ``frames``, ``points``, ``check_points``,
        ``observations``, ``rejected``, ``sigma0``, ``iterations``, ``converged``,
        ``solver``, ``rms_residual_px`` (per frame), ``check_rms_m`` (per frame) and
        ``check_rms_total_m`` (None without check points).

    Raises
    ------
    InputError
        If an input cannot be read, the observations refer to frames or points the other
        files do not have, or ``out`` is refused.
    """
    if client is not None or scheduler:
        from ..runtime import dask_client

        with dask_client(client, scheduler) as c:
            return c.submit(adjust_files, frames_path, points_path, obs_path, out, robust=robust, snooping=snooping,
                            tie_height_sigma=tie_height_sigma, overwrite=overwrite, pure=False).result()
    frames, specs = read_frames(frames_path)
    points = read_points(points_path)
    obs = read_observations(obs_path)
    final = check_output(out, inputs=(frames_path, points_path, obs_path), overwrite=overwrite)
    if not os.path.isdir(os.path.dirname(final)):
        raise InputError(final, "the output's parent directory does not exist")
    if len(obs) and obs.frame.max() >= len(frames):
        raise InputError(obs_path, f"refers to frame {int(obs.frame.max())}, but {frames_path} has {len(frames)}")
    unknown = np.setdiff1d(obs.point, points.id)
    if unknown.size:
        raise InputError(obs_path, f"refers to {unknown.size} point id(s) not in {points_path}, e.g. {int(unknown[0])}")
    used = points.subset(points.role != "check")
    check = points.subset(points.role == "check")
    problem, _ = build_problem(frames, used, obs, tie_height_sigma=tie_height_sigma)
    options = AdjustOptions(max_iter=20, tol=1e-3, robust=robust, snooping=snooping)
    result = adjust(problem, options)
    out = temporary_sibling(final)
    try:
        summary = _write_outputs(out, frames, specs, used, check, obs, result)
        write_marker(out, "adjust")
        commit_output(out, final, overwrite=overwrite)
    except BaseException:
        remove(out)
        raise
    return summary


def _write_outputs(out, frames, specs, used, check, obs, result) -> dict:
    os.makedirs(out)
    write_frames(os.path.join(out, "frames.json"), specs, result.params, result.param_cov)
    write_points(os.path.join(out, "points.csv"), used, result.ground)
    keep = np.isin(obs.point, used.id)
    o = obs.subset(keep)
    buf = io.StringIO(newline="")
    w = csv.writer(buf)
    w.writerow(["frame", "point", "x", "y", "vx", "vy", "normalized", "redundancy", "active"])
    nr = result.normalized_residuals if result.normalized_residuals is not None else np.full(len(o), np.nan)
    rd = result.redundancy if result.redundancy is not None else np.full(len(o), np.nan)
    rd = rd.sum(axis=1) if np.ndim(rd) == 2 else rd
    for i in range(len(o)):
        w.writerow([int(o.frame[i]), int(o.point[i]), o.col[i], o.row[i], *result.residuals[i], nr[i], rd[i],
                    bool(result.obs_active[i])])
    write_text(os.path.join(out, "residuals.csv"), buf.getvalue())
    rms_frame = []
    for k in range(len(frames)):
        m = (o.frame == k) & result.obs_active
        r = result.residuals[m]
        rms_frame.append(float(np.sqrt(np.mean(np.sum(r**2, axis=1)))) if r.size else float("nan"))
        residual_svg(os.path.join(out, f"residuals_frame{k}.svg"), np.stack([o.col[o.frame == k], o.row[o.frame == k]], 1),
                     result.residuals[o.frame == k], result.obs_active[o.frame == k])
    checks = check_errors(frames, result.params, check, obs) if len(check) else None
    summary = {
        "frames": len(frames), "points": len(used), "check_points": len(check), "observations": int(len(o)),
        "rejected": int((~result.obs_active).sum()), "sigma0": float(result.sigma0), "iterations": result.iterations,
        "converged": bool(result.converged), "solver": result.solver,
        "rms_residual_px": rms_frame,
        "check_rms_m": None if checks is None else [checks.rms(k) for k in range(len(frames))],
        "check_rms_total_m": None if checks is None else checks.rms(),
    }
    report = [f"# Block adjustment\n\n{len(frames)} frame(s), {len(used)} ground points, {len(o)} observations "
              f"({summary['rejected']} rejected); sigma0 = {result.sigma0:.3f}; {result.iterations} iterations"
              f" ({'converged' if result.converged else 'not converged'}); solver {result.solver}.\n\n",
              "| frame | RMS residual (px) | check RMS (m) |\n|---:|---:|---:|\n"]
    for k in range(len(frames)):
        c = "" if checks is None else f"{checks.rms(k):.2f}"
        report.append(f"| {k} | {rms_frame[k]:.3f} | {c} |\n")
    if checks is not None:
        report.append(f"\nCheck points overall: {checks.rms():.2f} m RMS over {np.isfinite(checks.error).sum()} observations.\n")
    write_text(os.path.join(out, "report.md"), "".join(report))
    write_text(os.path.join(out, "summary.json"), json.dumps(summary, indent=1))
    return summary
