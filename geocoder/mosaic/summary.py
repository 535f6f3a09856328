"""What a mosaic job reports: :class:`MosaicSummary` (the CLI's lines, the store's ``attrs["summary"]``)
and the figures of the adjustment and the seams that fill it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .diagnostics import pair_mismatch, residual_bins, scene_precision, seam_table


@dataclass
class MosaicSummary:
    """What the CLI prints and the store keeps (``attrs["summary"]``).

    Attributes
    ----------
    scenes : list of str
        The scenes, in the order of the block.
    control_points : list of int
        Control points found per scene.
    pairs : list of dict
        Overlapping pairs: scene indices ``i``, ``j``, their tie points ``ties`` and ``overlap``,
        the share of scene ``i`` inside scene ``j`` (from the placements on the reference).
    left_out : dict
        Scene index -> why it was left out of the block.
    sigma0 : float
        A-posteriori sigma of unit weight of the block adjustment.
    iterations : int
        Iterations of the block adjustment.
    rms_px : list of float
        RMS image residual per scene, in pixels.
    rays : dict
        Number of ground points by the number of scenes that see them.
    seam_step : list of float
        RMS grey-value step at the tie points before and after the radiometric balance.
    shape : tuple of int
        Rows and columns of the mosaic.
    seconds : dict
        Wall time per stage.
    block : list of int
        Scene index of every scene in the block (the order of ``rms_px``, ``precision_px``,
        ``observations``, ``residual_bins``, ``footprints`` and the store's ``source``).
    precision_px : list of float
        Per block scene, the RMS standard deviation of its adjusted position over its
        footprint (scene pixels; NaN when the adjustment gave no covariances).
    observations : list of int
        Per block scene, its image observations kept by the robust adjustment.
    residual_bins : list of list
        Per block scene, the mean residual of its observations in 3 x 3 cells of the scene:
        ``[col, row, rx, ry, n]``, the cell's mean position in output pixels, its mean residual
        in scene pixels and the number of observations.
    footprints : list of list
        Per block scene, its outline in output pixels (``[col, row]`` points).
    seam_mode : str
        How the seams were drawn: ``"centre"`` or ``"least-cost"``.
    seams : list of dict
        Per pair of scenes that meet along a seam: ``i``, ``j`` (scene indices), ``pixels``
        (its length in pixel edges), ``grey_step`` (RMS difference of the two balanced scenes
        along it), ``grey_bias``, and ``tie_mismatch_px`` (RMS disagreement of the two at their
        common tie points after the adjustment, :func:`~geocoder.mosaic.diagnostics.pair_mismatch`).
    seam_grey_step : float
        RMS grey-value step along all seams.
    seam_cells_moved : int
        Coarse cells the least-cost cut gave another scene than the centre rule.
    check_points : list of int
        Control points withheld as check points, per scene (empty without ``check_points``).
    check_rmse_px : list of float
        RMS of the check points' residuals (scene pixels) through the adjusted model, per scene
        (NaN for a scene without check points or out of the block).
    job : dict
        The job's tile tasks of this run (:meth:`geocoder.pipeline.job.Job.report`): ``resumed``,
        ``tile_tasks``, ``run``, ``skipped`` (finished by an earlier, interrupted run),
        ``recomputed`` and ``recomputed_fraction``; the dense refinement's tiles are not counted.
    placed : dict
        Scene index -> how its position was found: ``"reference"`` (matched on the
        reference), ``"georeference"`` (no reference: the scene's own), ``"via scene k"`` (not found there; matched on scene ``k``, its mapping
        chained through that scene's, :mod:`geocoder.mosaic.placement`) or ``"not placed"``.
    dense_refined : list of str
        Per block scene, how ``dense=True`` refined it: ``"reference"`` (a control scene, against
        the reference), ``"via i, j"`` (against its refined neighbours, scene indices;
        :mod:`geocoder.mosaic.dense_neighbours`) or ``"not"``. Empty without ``dense``.
    given_file : str
        The ``control`` CSV (empty without one).
    given_points : list of int
        Per scene, the CSV's control points the adjustment used (those withheld as check
        points are counted in ``check_points``); empty without a CSV.
    given_rmse_px : list of float
        Per scene, the RMS residual (scene pixels) of those points: their measured pixel
        against their map coordinates through the adjusted model (NaN without points or out
        of the block).
    given_residuals : list of list
        Every point of the ``control`` CSV: ``[id, scene, residual px, role]`` (its scene pixel
        against its map position through the adjusted model; None out of the block; role
        ``"control"`` or ``"check"``). Empty without a CSV.
    rejected : dict
        Image observations the adjustment left out: ``robust`` (by the robust re-weighting)
        and ``snooping`` (by Baarda's data snooping after it, one per round).
    point_sigma_px : dict
        ``tie`` and ``control``: the median, 95th percentile and largest standard deviation
        (reference pixels, the larger of x and y) of the adjusted ground points' map
        positions; empty when the block was too large for the covariances. Every point's are
        in the store's group ``points`` (:func:`geocoder.mosaic.block.point_table`).
    georeference_sigma_px : float or None
        Without a reference and a control CSV: the block's control is the scenes'
        georeferences, observed with this standard deviation (scene pixels); None otherwise.
    """

    scenes: list[str]
    control_points: list[int] = field(default_factory=list)
    pairs: list[dict] = field(default_factory=list)
    left_out: dict = field(default_factory=dict)
    sigma0: float = float("nan")
    iterations: int = 0
    rms_px: list[float] = field(default_factory=list)
    rays: dict = field(default_factory=dict)
    seam_step: list[float] = field(default_factory=list)
    shape: tuple[int, int] = (0, 0)
    seconds: dict = field(default_factory=dict)
    block: list[int] = field(default_factory=list)
    precision_px: list[float] = field(default_factory=list)
    observations: list[int] = field(default_factory=list)
    residual_bins: list[list] = field(default_factory=list)
    footprints: list[list] = field(default_factory=list)
    seam_mode: str = "centre"
    seams: list[dict] = field(default_factory=list)
    seam_grey_step: float = float("nan")
    seam_cells_moved: int = 0
    check_points: list[int] = field(default_factory=list)
    check_rmse_px: list[float] = field(default_factory=list)
    job: dict = field(default_factory=dict)
    placed: dict = field(default_factory=dict)
    dense_refined: list[str] = field(default_factory=list)
    given_file: str = ""
    given_points: list[int] = field(default_factory=list)
    given_rmse_px: list[float] = field(default_factory=list)
    given_residuals: list[list] = field(default_factory=list)
    rejected: dict = field(default_factory=dict)
    point_sigma_px: dict = field(default_factory=dict)
    georeference_sigma_px: float | None = None

    def lines(self) -> list[str]:
        """The summary as the lines the CLI prints.

        Returns
        -------
        list of str
        """
        kept = len(self.scenes) - len(self.left_out)
        return [
            f"scenes: {len(self.scenes)} ({kept} in the block); control points per scene {self.control_points}",
            *([f"no reference: the block is controlled by the scenes' georeferences (sigma "
               f"{self.georeference_sigma_px:g} px), as accurate as they are on average"]
              if self.georeference_sigma_px is not None else []),
            f"overlapping pairs: {len(self.pairs)}, tie points (overlap) "
            + ", ".join(f"{p['i']}-{p['j']}: {p['ties']}" + (f" ({p['overlap']:.0%})" if "overlap" in p else "") for p in self.pairs),
            *(["placed: " + ", ".join(f"{k} {how}" for k, how in self.placed.items())]
              if any(how not in ("reference", "georeference") for how in self.placed.values()) else []),
            *(f"left out: {self.scenes[int(k)]}: {why}" for k, why in self.left_out.items()),
            "ground points by rays: " + ", ".join(f"{k}: {v}" for k, v in self.rays.items()),
            f"block adjustment: sigma0 {self.sigma0:.3f}, {self.iterations} iterations, RMS residual per scene (px) "
            + ", ".join(f"{r:.3f}" for r in self.rms_px),
            *([f"observations left out: {self.rejected.get('robust', 0)} by the robust weights, "
               f"{self.rejected.get('snooping', 0)} by data snooping"] if self.rejected else []),
            *(["ground point precision (reference px, median / 95 % / max): "
               + ", ".join(f"{k} {v[0]:.3f} / {v[1]:.3f} / {v[2]:.3f}" for k, v in self.point_sigma_px.items())]
              if self.point_sigma_px else []),
            *([f"control points from {self.given_file}: {sum(self.given_points)} used, per scene {self.given_points}, "
               "RMS residual per scene (px) " + ", ".join(f"{r:.3f}" for r in self.given_rmse_px)] if self.given_file else []),
            *([f"check points (withheld): {sum(self.check_points)}, RMS residual per scene (px) "
               + ", ".join(f"{r:.3f}" for r in self.check_rmse_px)] if sum(self.check_points) else []),
            *([f"radiometric balance: grey-value step at the tie points {self.seam_step[0]:.3g} before, "
               f"{self.seam_step[1]:.3g} after (RMS, all bands)"] if self.seam_step else []),
            *([f"seams ({self.seam_mode}): grey-value step along the seams {self.seam_grey_step:.3g} (RMS), "
               f"tie-point mismatch per pair (px) "
               + ", ".join(f"{p['i']}-{p['j']}: {p.get('tie_mismatch_px', float('nan')):.3f}" for p in self.seams)]
              if self.seams else []),
            *(["dense refinement per scene: " + ", ".join(f"{self.scenes[k]}: {how}" for k, how in zip(self.block, self.dense_refined))]
              if self.dense_refined else []),
            f"mosaic: {self.shape[0]} x {self.shape[1]} px",
            *([f"resumed: {self.job['skipped']} of {self.job['tile_tasks']} tile tasks finished earlier, "
               f"at most {self.job['recomputed']} ({self.job['recomputed_fraction']:.1%}) computed again"]
              if self.job.get("resumed") else []),
            "time: " + ", ".join(f"{k} {v:.1f} s" for k, v in self.seconds.items()),
        ]


def point_sigma(points: np.ndarray) -> dict:
    """Median, 95th percentile and largest point sigma (the larger axis) of tie and control points."""
    sigma = np.fmax(points[:, 4], points[:, 5])
    out = {}
    for name, kind in (("tie", 0.0), ("control", 1.0)):
        v = sigma[(points[:, 2] == kind) & np.isfinite(sigma)]
        if v.size:
            out[name] = [round(float(np.median(v)), 5), round(float(np.percentile(v, 95)), 5), round(float(v.max()), 5)]
    return out


def adjustment_figures(summary: MosaicSummary, problem, result, models: list, shapes: list, to_map: list,
                        to_out: list, dem=None) -> None:
    """Per block scene: precision, observations kept and binned residuals (into ``summary``).

    ``to_map`` and ``to_out``: every scene's pixel -> map and pixel -> output pixel mappings
    (the bins' positions are output pixels, their residuals scene pixels).
    """
    covs = result.param_cov if result.param_cov is not None else [None] * len(models)
    summary.precision_px, summary.observations, summary.residual_bins = [], [], []
    for n, ((model, params), shape, f) in enumerate(zip(models, shapes, to_map)):
        h, w = shape
        ys, xs = np.meshgrid(np.linspace(0, h - 1, 5), np.linspace(0, w - 1, 5), indexing="ij")
        ex, ny = f(xs.ravel(), ys.ravel())
        hz = np.zeros(ex.size) if dem is None else dem(ex, ny)
        summary.precision_px.append(scene_precision(model, params, covs[n], np.column_stack([ex, ny, hz])))
        mine = (problem.obs_frame == n) & result.obs_active
        summary.observations.append(int(mine.sum()))
        bins = residual_bins(problem.obs_xy[mine], result.residuals[mine], shape)
        if bins:
            cx, cy = to_out[n](np.array([b[0] for b in bins]), np.array([b[1] for b in bins]))
            bins = [[round(float(x), 2), round(float(y), 2), *b[2:]] for x, y, b in zip(cx, cy, bins)]
        summary.residual_bins.append(bins)


def seam_figures(summary: MosaicSummary, stats: list[dict], block: list[int], problem, result) -> None:
    """The seams per pair of scenes (grey step from the tiles, mismatch from the adjustment) into ``summary``."""
    table = seam_table(stats, block)
    index = {k: n for n, k in enumerate(block)}
    keys = [(index[r["i"]], index[r["j"]]) for r in table]
    mismatch = pair_mismatch(problem.obs_frame, problem.obs_point, result.residuals, result.obs_active, keys)
    for r, m in zip(table, mismatch):
        r["tie_mismatch_px"] = m
    summary.seams = table
    n = sum(r["pixels"] for r in table)
    summary.seam_grey_step = float(np.sqrt(sum(r["pixels"] * r["grey_step"] ** 2 for r in table) / n)) if n else float("nan")


__all__ = ["MosaicSummary", "adjustment_figures", "point_sigma", "seam_figures"]
