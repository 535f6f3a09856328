"""``mosaic(scenes, reference=...)``: many overlapping scenes -> one block adjustment -> one mosaic.

1. Every scene and the reference are ingested to Zarr (tile-parallel), inside the job directory.
2. Every scene is matched against the reference (the registration's coarse alignment,
   Foerstner points and robust correspondence, tile-parallel): its footprint, and control
   points for the scenes allowed to have them. A scene not found there is matched against
   the placed scenes it may overlap, its mapping chained through theirs, round after round
   while one places a scene (:mod:`geocoder.mosaic.placement`); it has no control points.
3. Every pair of scenes whose footprints overlap is matched the same way: tie points.
   Steps 2 and 3 run as a few rounds for all pairs at once (:mod:`geocoder.mosaic.matching`):
   the interest points of every scene in one stage, then per batch one stage each for the
   coarse alignments and the correspondence passes, one task per base tile of every pair.
4. The block (one :class:`~geocoder.adjust.models.MapPolynomial` per scene) is adjusted on
   one node with robust re-weighting; scenes tied to no control are reported and left out.
5. The output grid (the reference's CRS and pixel, the union of the footprints) is written one
   task per tile: each task maps its pixels into every scene through the adjusted models,
   samples the ORIGINAL scenes once, and blends them across seams, feathered; ``source`` says
   which scene each pixel comes from. The seams are nearest each scene's centre
   (``seams="centre"``) or, by default, cut on a coarse grid of the output along the least
   grey-value difference of each overlapping pair (:mod:`geocoder.mosaic.seamplan`, one task per
   coarse window, then the cut on one node; every output tile reads its window of the label map).
6. The summary keeps, per scene, the adjustment's residuals (binned) and precision and its
   footprint, and per pair the seam's length, grey-value step and tie-point mismatch: what
   :func:`geocoder.mosaic.report.write_report` draws.
"""

from __future__ import annotations

import contextvars
import json
import logging
import math
import os
import tempfile
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field, replace

import dask
import dask.array as da
import numpy as np
import xarray as xr
from affine import Affine

from .. import progress
from .._version import __version__
from ..adjust.models import RPC
from ..cog import to_cog
from ..conventions import georeference, status_attrs
from ..errors import GeocoderError, InputError
from ..geometry import pixel_to_world, world_to_pixel
from ..kernels.interest import InterestPoints
from ..kernels.polynomial import fit_polymap
from ..multiscales import write_overviews
from ..options import get_option
from ..outputs import check_output, commit_output, product_attrs
from ..pipeline.coarse import georeference_prior
from ..pipeline.job import Job, JobRun, fingerprint, input_identity
from ..pipeline.register import RegisterOptions, _Timer, ingest_all, open_job
from ..runtime import dask_client
from ..scene import WindowReader, open_scene, scene_transform
from ..status import Status, positioned
from ..tiles import TileGrid
from .block import POINT_COLUMNS, Matches, build_problem, connected_scenes, point_table, solve
from .compose import NO_SOURCE, blend, centre_score
from .control import DEFAULT_SIGMA_PX, read_control
from .dense_neighbours import refine_by_neighbours
from .diagnostics import footprint_outline, pair_mismatch, residual_bins, scene_precision, seam_table
from .georef import (
    GEOREFERENCE_SIGMA_PX,
    georeference_control,
    georeference_mappings,
    virtual_reference,
)
from .heights import MapDEM, ref_to_scene_prior
from .layers import field_layers, model_layers, pixel_sigma, sample_field, scene_uncertainty
from .matching import PairSpec, match_pairs, scene_points
from .outgrid import Reprojected, from_map, other_grid, to_map
from .placement import Placement, affine_between, footprint_from_model, overlap_fraction, place_by_neighbours
from .projection import project_window
from .radiometry import seam_step, solve_balance
from .refine import refine_scene
from .seamplan import plan_seams, read_labels
from .sensors import KINDS, model_from_dict, model_to_dict, scene_sensor, sensor_model

log = logging.getLogger("geocoder")


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


def _to_map(mapping_to_ref, transform: Affine):
    def f(x, y):
        rx, ry = mapping_to_ref(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        return pixel_to_world(transform, rx, ry)

    return f


def _shifted(to_ref, origin: tuple[int, int]):
    """Scene pixel -> output pixel, from scene pixel -> reference pixel and the output's origin."""
    def f(x, y):
        rx, ry = to_ref(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        return rx - origin[0], ry - origin[1]

    return f


def _adjustment_figures(summary: MosaicSummary, problem, result, models: list, shapes: list, to_map: list,
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


def _point_sigma(points: np.ndarray) -> dict:
    """Median, 95th percentile and largest point sigma (the larger axis) of tie and control points."""
    sigma = np.fmax(points[:, 4], points[:, 5])
    out = {}
    for name, kind in (("tie", 0.0), ("control", 1.0)):
        v = sigma[(points[:, 2] == kind) & np.isfinite(sigma)]
        if v.size:
            out[name] = [round(float(np.median(v)), 5), round(float(np.percentile(v, 95)), 5), round(float(v.max()), 5)]
    return out


def _seam_figures(summary: MosaicSummary, stats: list[dict], block: list[int], problem, result) -> None:
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


def _through_map(to_ref, transform: Affine, grid: Affine | Reprojected):
    """Scene pixel -> output pixel of any output grid, through the reference's map coordinates."""
    def f(x, y):
        rx, ry = to_ref(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        return from_map(grid, *pixel_to_world(transform, rx, ry))

    return f


def _output_crs(ref: xr.DataArray, reference, resolution: float | None, crs) -> str | None:
    """``crs`` as WKT, None where it is the reference's; refused without a georeferenced reference."""
    if resolution is None and crs is None:
        return None
    if not ref.attrs.get("georeferenced"):
        raise InputError(reference, "is not georeferenced: an output resolution or CRS needs the reference's CRS")
    if crs is None:
        return None
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    try:
        out = CRS.from_user_input(crs)
    except CRSError:
        raise ValueError(f"crs: {crs!r} is not a coordinate reference system pyproj knows") from None
    return None if out == CRS.from_user_input(ref.rio.crs) else out.to_wkt()


def _scene_xy(model, params, transform: Affine | Reprojected, window: tuple[int, int, int, int], located: dict | None,
              origin: tuple[int, int] | Affine, heights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Position in one scene of every pixel of an output window: its adjusted model, or its
    dense field where that matched or filled the pixel.

    ``transform``: the output grid (an affine, or :class:`~geocoder.mosaic.outgrid.Reprojected`);
    ``origin``: the output grid's pixel (0, 0) in reference pixels (``col, row``), or the
    reference's transform for an output grid of another pixel size or CRS (the field is then
    sampled at each output pixel's reference position, :func:`~geocoder.mosaic.layers.sample_field`);
    ``heights``: the window's ground heights (the DEM's; 0 without).
    """
    import zarr

    r0, r1, c0, c1 = window
    ys, xs = np.mgrid[r0:r1, c0:c1].astype(np.float64)
    ex, ny = to_map(transform, xs, ys)
    hz = np.zeros(ex.shape) if heights is None else np.asarray(heights, dtype=np.float64).reshape(ex.shape)
    x, y = project_window(model, params, ex, ny, hz)
    if located is None:
        return x, y
    if isinstance(origin, Affine):  # another pixel size or CRS: the field sampled at the reference pixels
        rx, ry = world_to_pixel(origin, ex, ny)
        dx, dy, good, *_ = sample_field(located, rx, ry)
        return np.where(good, rx + dx, x), np.where(good, ry + dy, y)
    # the window in the field's frame (reference pixels, offset by the field's origin)
    fr0, fc0 = r0 + origin[1] - located["row0"], c0 + origin[0] - located["col0"]
    a0, a1 = max(fr0, 0), min(fr0 + (r1 - r0), located["shape"][0])
    b0, b1 = max(fc0, 0), min(fc0 + (c1 - c0), located["shape"][1])
    if a0 >= a1 or b0 >= b1:
        return x, y
    g = zarr.open_group(located["store"], mode="r")
    dx, dy, status = (np.asarray(g[n][a0:a1, b0:b1]) for n in ("dx", "dy", "status"))
    good = positioned(status)
    sl = (slice(a0 - fr0, a1 - fr0), slice(b0 - fc0, b1 - fc0))
    rx = np.arange(b0, b1)[None, :] + located["col0"]  # reference pixel of each field sample
    ry = np.arange(a0, a1)[:, None] + located["row0"]
    x[sl] = np.where(good, rx + dx, x[sl])
    y[sl] = np.where(good, ry + dy, y[sl])
    return x, y


def _mosaic_tile(store: str, window: tuple[int, int, int, int], transform: Affine | Reprojected, models: list, readers: list,
                 shapes: list, feather_px: float, method: str, balance: np.ndarray, fields: list,
                 origin: tuple[int, int] | Affine, boxes: np.ndarray, seams: dict | None = None,
                 grid_shape: tuple[int, int] | None = None, dem=None, covs: list | None = None,
                 unmodelled: np.ndarray | None = None) -> dict:
    """Compute and write one output tile; returns the pixels covered and its seam statistics.

    Only the scenes whose footprint box (``boxes``: ``row0, row1, col0, col1`` in output
    pixels, with a margin) meets the tile are sampled: time and memory per tile depend on how
    many scenes overlap it, not on the size of the block.

    ``seams``: the coarse label map (:func:`~geocoder.mosaic.seamplan.plan_seams`); without
    it, the seams are nearest each scene's centre (:func:`~geocoder.mosaic.compose.blend`).
    The tile is computed with one more row and column (inside the mosaic) so that a seam
    between this tile's last pixel and the next tile's first is counted here, once.

    The tile's ``status``, ``sigma_x`` and ``sigma_y`` are those of each pixel's ``source``
    scene (:mod:`geocoder.mosaic.layers`), from ``covs`` (every scene's parameter covariance,
    or None) and ``unmodelled`` (``(K, 2)``, its unmodelled variance, scene pixels squared).

    Returns
    -------
    dict
        ``covered``: pixels with a source; ``seams``: ``(a, b) -> [n, sum d, sum d^2]`` over
        the tile's pixels whose right or lower neighbour comes from another scene, ``d`` the
        difference of the two balanced scenes' grey values (mean of the bands) at the pixel.
    """
    import zarr

    from .seams import label_weights, seam_pairs, upsample_labels

    r0, r1, c0, c1 = window
    H, W = grid_shape if grid_shape is not None else (r1, c1)
    e1, f1 = min(r1 + 1, H), min(c1 + 1, W)  # one more row and column, for the seams at the tile's edge
    ext = (r0, e1, c0, f1)
    near = np.flatnonzero((boxes[:, 0] < e1) & (boxes[:, 1] > r0) & (boxes[:, 2] < f1) & (boxes[:, 3] > c0))
    heights = None
    if dem is not None:  # every pixel's ground height, mapped into each scene with it
        ys, xs = np.mgrid[r0:e1, c0:f1].astype(np.float64)
        heights = dem(*to_map(transform, xs, ys))
    nb = readers[0].shape[0] if readers else 1
    values = np.full((near.size, nb, e1 - r0, f1 - c0), np.nan, dtype=np.float32)
    scores = np.full((near.size, e1 - r0, f1 - c0), np.nan)
    codes = np.full((near.size, e1 - r0, f1 - c0), Status.OUTSIDE, dtype=np.uint8)
    sigmas = np.full((near.size, 2, e1 - r0, f1 - c0), np.nan, dtype=np.float32)
    for i, k in enumerate(near):
        (model, params), reader, shape = models[k], readers[k], shapes[k]
        x, y = _scene_xy(model, params, transform, ext, fields[k], origin, heights)
        s = centre_score(x, y, shape)
        if not np.any(s <= 1.0):
            continue
        scores[i] = np.where(s <= 1.0, s, np.nan)
        values[i] = balance[k, :, 0, None, None] * reader.sample(x, y, method=method) + balance[k, :, 1, None, None]
        codes[i], sx, sy = field_layers(fields[k], ext, origin, transform)
        cov_model, inverse = model_layers(model, params, None if covs is None else covs[k], transform, ext, dem,
                                          None if unmodelled is None else unmodelled[k])
        sigmas[i] = pixel_sigma(codes[i], cov_model, inverse, sx, sy)
    feather = 2.0 * feather_px / max(min(min(s) for s in shapes), 1)
    mosaic, source, _ = blend(values, scores, feather=feather)
    if near.size:  # blend counts the scenes of this tile; the store names them by block index
        source = np.where(source == NO_SOURCE, NO_SOURCE, near[np.minimum(source, near.size - 1)]).astype(np.uint16)
    if seams is not None and near.size:
        halo = math.ceil(feather_px / 2.0) + 2
        big = (r0 - halo, e1 + halo, c0 - halo, f1 + halo)
        cells, a0, b0 = read_labels(seams, big)
        label = upsample_labels(cells, a0, b0, big, seams["factor"], (H, W))
        weight = label_weights(label, near, feather=feather_px)[:, halo:-halo, halo:-halo]
        valid = np.all(np.isfinite(values), axis=1) & np.isfinite(scores)
        weight = np.where(valid, weight, 0.0)
        total = weight.sum(axis=0)
        own = label[halo:-halo, halo:-halo]
        pos = np.searchsorted(near, own)
        hit = (own != NO_SOURCE) & (near[np.minimum(pos, near.size - 1)] == own)
        own_valid = hit & np.take_along_axis(valid, np.minimum(pos, near.size - 1)[None], axis=0)[0]
        use = total > 0  # elsewhere (no label, or the labelled scenes have no data): the centre rule
        w = np.divide(weight, total, out=np.zeros_like(weight), where=use)
        labelled = np.einsum("khw,kbhw->bhw", w, np.where(valid[:, None], values, 0.0)).astype(np.float32)
        mosaic = np.where(use[None], labelled, mosaic)
        best = near[np.argmax(weight, axis=0)].astype(np.uint16)
        source = np.where(own_valid, own, np.where(use, best, source)).astype(np.uint16)
    status = np.full(source.shape, Status.OUTSIDE, dtype=np.uint8)
    sigma = np.full((2, *source.shape), np.nan, dtype=np.float32)
    if near.size:  # the layers of each pixel's source scene
        has = source != NO_SOURCE
        at = np.minimum(np.searchsorted(near, source), near.size - 1)[None]
        status = np.where(has, np.take_along_axis(codes, at, axis=0)[0], status)
        sigma = np.where(has, np.take_along_axis(sigmas, at[:, None], axis=0)[0], sigma)
    stats: dict = {}
    if near.size:
        rr, cc, a, b = seam_pairs(source, rows=r1 - r0, cols=c1 - c0)
        if rr.size:
            index = np.full(int(max(a.max(), b.max(), near.max())) + 1, -1)
            index[near] = np.arange(near.size)
            va = values[index[a], :, rr, cc].mean(axis=-1)
            vb = values[index[b], :, rr, cc].mean(axis=-1)
            d = va - vb
            ok = np.isfinite(d)
            a, b = a.astype(np.int64), b.astype(np.int64)
            lo, hi = np.minimum(a, b)[ok], np.maximum(a, b)[ok]
            d = np.where(a[ok] == lo, d[ok], -d[ok])
            for p in np.unique(lo * 65536 + hi):
                sel = (lo * 65536 + hi) == p
                stats[(int(p // 65536), int(p % 65536))] = [int(sel.sum()), float(d[sel].sum()), float((d[sel] ** 2).sum())]
    g = zarr.open_group(store, mode="r+")
    g["mosaic"][:, r0:r1, c0:c1] = mosaic[:, : r1 - r0, : c1 - c0]
    g["source"][r0:r1, c0:c1] = source[: r1 - r0, : c1 - c0]
    g["status"][r0:r1, c0:c1] = status[: r1 - r0, : c1 - c0]
    g["sigma_x"][r0:r1, c0:c1] = sigma[0, : r1 - r0, : c1 - c0]
    g["sigma_y"][r0:r1, c0:c1] = sigma[1, : r1 - r0, : c1 - c0]
    if heights is not None:
        g["height"][r0:r1, c0:c1] = heights[: r1 - r0, : c1 - c0].astype(np.float32)
    return {"covered": int((source[: r1 - r0, : c1 - c0] != NO_SOURCE).sum()), "seams": stats}


def mosaic(
    scenes: list,
    *,
    reference=None,
    out: str | os.PathLike | None = None,
    order: int = 2,
    tile: int | None = None,
    output_tile: int | None = None,
    control_scenes: list[int] | None = None,
    check_points: float = 0.0,
    control: str | os.PathLike | None = None,
    resolution: float | None = None,
    crs=None,
    feather: float = 8.0,
    seams: str = "least-cost",
    resampling: str = "bilinear",
    balance: bool = True,
    client=None,
    scheduler: str | None = None,
    overwrite: bool = False,
    cog: str | os.PathLike | None = None,
    dense: bool | str = False,
    model: str = "polynomial",
    dem: str | os.PathLike | None = None,
    report: str | os.PathLike | None = None,
    resume: bool = True,
    show_progress=None,
    georeference_sigma: float = GEOREFERENCE_SIGMA_PX,
) -> xr.Dataset:
    """Adjust overlapping scenes as one block on a reference and write one seamless mosaic.

    Parameters
    ----------
    scenes : list of str, PathLike
        GeoTIFF/COG/Zarr scenes. A georeference is not needed: each is found on the
        reference, or, where the reference cannot find it (the scene small next to it, the
        reference untextured, cloudy or nodata there, or the scene partly outside it), on the
        scenes already placed that it overlaps: tried against those its georeference or RPCs
        say it overlaps, or against every placed scene if it carries neither. Its mapping to
        the reference is chained through that scene's (``summary["placed"]``: ``"reference"``,
        ``"via scene k"`` or ``"not placed"``); it has no control points of its own, the block
        adjustment carries it by its tie points. A scene found nowhere is reported in
        ``summary["left_out"]`` and left out.
    reference : str or PathLike, optional
        Orthoimage: the source of control points, the CRS of the scenes' models, and the
        output's CRS and pixel unless ``crs`` or ``resolution`` say otherwise. Without it
        (:mod:`geocoder.mosaic.georef`) the georeferenced scenes (at least one, all in one
        CRS) set the frame: the block is adjusted on a north-up grid of that CRS at their
        finest pixel (the output's grid unless ``crs`` or ``resolution`` say otherwise), each
        of them placed by its georeference, the others through their neighbours, all tied
        by tie points, and controlled by the ``control`` CSV or, without one, by the
        georeferences (see ``georeference_sigma``); ``dense`` then needs a reference and is
        refused, and the radiometric balance ties the scenes to each other only.
    out : str or PathLike, optional
        Zarr store to write (atomically; output safety as in :func:`geocoder.register`).
        Without it the mosaic is computed into memory.
    order : int
        Polynomial order of every scene's model (1-3).
    tile : int, optional
        Tile of all tile-parallel stages and of the output (a multiple of 64); default
        :func:`geocoder.get_option` ``("tile")`` (512 unless set).
    output_tile : int, optional
        Tile (and chunk) of the output grid, default ``tile``. The mosaic's pixels do not
        depend on it (to rounding): the seams are decided on a coarse grid, not per tile.
    control_scenes : list of int, optional
        Scenes whose reference matches serve as control points (default all); the others
        are placed by tie points only (sparse control). The ``control`` CSV's points count
        whatever this says: ``control_scenes=[]`` with a CSV is control given by hand only.
    check_points : float
        Share of every control scene's control points withheld from the adjustment as check
        points (every n-th; 0: none): their residuals through the adjusted models are the
        summary's ``check_rmse_px``, an accuracy the adjustment did not see. The ``control``
        CSV's points are withheld the same way, scene by scene.
    control : str or PathLike, optional
        Ground control points measured by hand: a CSV with a header and the columns
        ``scene`` (0-based index in ``scenes``, or the scene's file name), ``col``, ``row``
        (pixel in that scene, pixel centres at integers: the top-left pixel's centre is
        ``0, 0``), ``x``, ``y`` (map coordinates in the reference's CRS), optionally
        ``sigma`` (standard deviation of ``x`` and ``y``, map units; default half the
        reference's pixel) and ``id``. Each point is a control point of the block adjustment
        beside the reference's matches (the scene pixel observed with a precision of 0.3 px,
        :mod:`geocoder.mosaic.control`). A malformed file raises
        :class:`~geocoder.errors.InputError` naming the file, line and column before any
        work. The summary's ``given_points`` and ``given_rmse_px`` report them.
    resolution : float, optional
        The output's pixel size, in units of its CRS. Default: the reference's pixel grid
        itself. Given (or with ``crs``), the output is a north-up grid of square pixels
        aligned to multiples of ``resolution`` (pixel edges at ``k * resolution``), covering
        the scenes' footprints as the default does.
    crs : str, int or pyproj.CRS, optional
        The output's CRS (``"EPSG:32634"``, ``3857``, WKT...); default the reference's. The
        scenes' models stay in the reference's CRS: every output pixel is mapped there
        exactly (pyproj, per pixel, in its tile's task). Without ``resolution``, the pixel is
        the reference's pixel size measured in ``crs`` at the block's centre. With ``dense``,
        the fields (on the reference's grid) are sampled where each output pixel falls on it
        (bilinear, :func:`geocoder.mosaic.layers.sample_field`).
    feather : float
        Width of the blend across a seam, in output pixels.
    seams : {"least-cost", "centre"}
        Where the seams run. ``"centre"``: every pixel from the scene that sees it nearest
        its centre. ``"least-cost"``: that seam, then moved within a corridor around it onto
        the cut of least grey-value difference between the two scenes
        (:mod:`geocoder.mosaic.seams`), decided on a coarse grid of the output (cells of 8
        output pixels or more) and feathered across the label boundary in every tile.
    resampling : str
        Interpolator of the single resampling of every scene.
    balance : bool
        Radiometric balance: a gain and offset per scene and band, fitted to the reference's
        grey values at the control points and to each other's at the tie points.
    client, scheduler
        Where to run (as :func:`geocoder.register`).
    overwrite : bool
        Replace an existing ``out`` (and ``cog``) that geocoder wrote.
    cog : str or PathLike, optional
        Also write the mosaic as a Cloud-Optimized GeoTIFF (tile-parallel, with overviews;
        :func:`geocoder.cog.to_cog`).
    dense : bool
        Dense refinement: every control scene is matched pixel by pixel against the reference
        (the registration's dense stage, seeded by its control points, predicted by its
        adjusted model); where a pixel is matched or filled, the mosaic takes it from there
        instead of from the model (the line-to-line turbulence of airborne scanners, which
        no polynomial follows). Then, in rounds, every scene without control (or whose
        refinement failed) that shares tie points with refined scenes is matched the same way
        against those neighbours, brought onto the reference grid through their refined
        positions (:mod:`geocoder.mosaic.dense_neighbours`); the summary's ``dense_refined``
        says how each scene was refined. The fields are kept in the store (group
        ``dense/<n>``); scenes connected to no refined scene keep their model. ``"control"``:
        only the control scenes are refined.
    model : {"polynomial", "linescanner", "rpc"}
        Every scene's model in the block adjustment and the output: a polynomial of map
        coordinates of ``order``; the line scanner the scene carries (GeoTIFF tag
        ``GEOCODER_LINESCANNER`` or a ``geocoder simulate`` satellite store), its position
        and yaw adjusted (:data:`geocoder.mosaic.sensors.LINESCANNER_FREE`); or its RPCs
        with an affine bias correction in image space. A scene that carries neither RPCs nor
        a line scanner is placed blind on the reference; with a model that needs what it
        lacks, an :class:`~geocoder.errors.InputError` names it.
    dem : str or PathLike, optional
        DEM (heights in metres, ellipsoidal for the sensor models; reprojected to the
        reference's CRS if it has another): the ground heights of control and tie points,
        bilinear, and of every output pixel, which is mapped into each scene with its height.
        The store then holds ``height (y, x)``. Without it heights are 0.
    report : str or PathLike, optional
        Also write the report directory (:func:`geocoder.mosaic.write_report`: Markdown
        with the overlap graph, the adjustment and the seams, and figures); refused before
        the job if it exists and geocoder did not write it.
    resume : bool
        Continue the unfinished job writing ``out`` (same inputs, options and version):
        pairs, the adjustment and output tiles finished by an earlier, interrupted run are not
        computed again. False starts afresh.
    show_progress : Progress or bool, optional
        Progress receiver, as in :func:`geocoder.register`.
    georeference_sigma : float
        Without ``reference`` and ``control``: the standard deviation (scene pixels) of every
        scene's georeference, which then controls the block as a grid of 5 x 5 points per
        scene observed with it (the block lands where the georeferences say on average).

    Returns
    -------
    xarray.Dataset
        ``mosaic (band, y, x)`` float32, ``source (y, x)`` uint16 (index into
        ``attrs["scenes"]``, 65535 = none), ``status (y, x)`` uint8 (what the pixel's position
        in its source scene rests on, :class:`~geocoder.status.Status` with CF
        ``flag_values``/``flag_meanings``: ``matched`` or ``filled`` from the dense field,
        ``model`` (or ``blunder``, ``no_texture`` where the dense matcher rejected or could
        not match it) from the adjusted model, ``outside`` where no scene covers it),
        ``sigma_x``, ``sigma_y (y, x)`` float32 (standard deviation of that position along
        the output's columns and rows, output pixels: the dense match's where matched, else
        the adjustment's covariance propagated to the pixel plus the scene's mean squared
        residual; a feathered pixel's are its ``source`` scene's;
        :mod:`geocoder.mosaic.layers`), ``height (y, x)`` with a ``dem``, the output's CRS
        and transform (the reference's by default); ``attrs``: the adjusted ``models``
        (``models_crs``: their CRS, when not the output's), the ``radiometry`` (gain, offset
        per scene and band) and the ``summary`` (JSON). With ``out``, overview levels of every
        variable (``status`` and ``source`` nearest, the others averaged).
    """
    if not scenes:
        raise InputError("scenes", "no scenes given")
    if tile is None:
        tile = get_option("tile")
    if not 1 <= order <= 3:
        raise ValueError(f"order must be 1, 2 or 3, got {order}")
    if not 0.0 <= check_points < 1.0:
        raise ValueError(f"check_points must be in [0, 1), got {check_points}")
    if seams not in ("least-cost", "centre"):
        raise ValueError(f"seams must be 'least-cost' or 'centre', got {seams!r}")
    if model not in KINDS:
        raise ValueError(f"model must be one of {', '.join(KINDS)}, got {model!r}")
    if dense not in (False, True, "control"):
        raise ValueError(f"dense must be True, False or 'control', got {dense!r}")
    if resolution is not None and not (math.isfinite(resolution) and resolution > 0):
        raise ValueError(f"resolution must be a positive number, got {resolution!r}")
    if reference is None and dense:
        raise ValueError("dense refinement matches the scenes against a reference orthoimage: give reference")
    if not (math.isfinite(georeference_sigma) and georeference_sigma > 0):
        raise ValueError(f"georeference_sigma must be a positive number, got {georeference_sigma!r}")
    opts = RegisterOptions(tile=tile, order=order, dense=False)
    if output_tile is None:
        output_tile = tile
    if output_tile < 16 or output_tile % 16:
        raise ValueError(f"output_tile must be a multiple of 16, got {output_tile}")
    opts.validate()
    extra = [control] if control is not None else []  # the CSV is never written over either
    if reference is not None:
        extra.append(reference)
    if out is not None:
        out = check_output(out, inputs=(*scenes, *extra), overwrite=overwrite)
    if cog is not None:  # refused now, not after the job
        check_output(cog, inputs=(*scenes, *extra, *([out] if out is not None else [])), overwrite=overwrite)
    if report is not None:
        from ..reporting import require_matplotlib

        require_matplotlib()
        check_output(report, inputs=(*scenes, *extra, *([out] if out is not None else []), *([cog] if cog else [])),
                     overwrite=overwrite, option="report")
    opened = [open_scene(s, chunks=tile) for s in scenes]
    virtual = reference is None  # the frame from the scenes' georeferences (geocoder.mosaic.georef)
    ref = virtual_reference(opened, tile) if virtual else open_scene(reference, chunks=tile, grid=True)
    crs = _output_crs(ref, reference, resolution, crs)
    given = None
    if control is not None:  # read and checked now, before any work
        pixel = math.sqrt(abs((scene_transform(ref) or Affine.identity()).determinant))
        given = read_control(control, list(scenes), [(s.sizes["y"], s.sizes["x"]) for s in opened],
                             default_sigma=DEFAULT_SIGMA_PX * pixel)
    # what every scene carries (its footprint; the model when asked for): refused now, naming the scene
    carried = [scene_sensor(s, model) if model != "polynomial" else _carried(s) for s in scenes]
    if model != "polynomial" and not ref.attrs.get("georeferenced"):
        raise InputError(reference, f"is not georeferenced: the {model} model needs the reference's CRS")
    dem_scene = None
    if dem is not None:
        dem_scene = _open_dem(dem, ref, tile)
    bands = {s.sizes["band"] for s in opened}
    if len(bands) != 1:
        raise InputError(scenes[0], f"the scenes have different band counts {sorted(bands)}; give scenes with the same bands")
    transform = scene_transform(ref) or Affine.identity()
    summary = MosaicSummary(scenes=[s.attrs["source"] for s in opened], seam_mode=seams)
    timer = _Timer(summary)  # type: ignore[arg-type]
    allowed = set(range(len(scenes)) if control_scenes is None else control_scenes)
    # the inputs' content identity and the version, as register's: a scene, reference or DEM
    # replaced at the same path, or another geocoder, must not reuse the job's finished work
    key = fingerprint(scenes=[input_identity(s) for s in scenes],
                      reference=["georeferences", georeference_sigma] if virtual else input_identity(reference),
                      dem=None if dem is None else input_identity(dem), options=repr(opts), output_tile=output_tile,
                      control=sorted(allowed), check_points=check_points, feather=feather, seams=seams, resampling=resampling, balance=balance,
                      dense=dense, model=model, version=__version__,
                      **({} if given is None else {"given": [input_identity(control), given.digest]}),
                      **({} if resolution is None and crs is None else {"grid": [resolution, crs]}))
    job = open_job(out, key, resume) if out is not None else Job(tempfile.mkdtemp(prefix=".geocoder-job-"), key)
    if job.resumed:
        log.info("resuming the job in %s", job.path)
    with JobRun(job, resumable=out is not None) as run, progress.reporting(show_progress), \
            dask_client(client, scheduler) as c:
        run.connected = c.scheduler.address
        progress.current().message(f"Dask dashboard: {c.dashboard_link}")
        with timer("ingest"):
            named = {**({} if virtual else {"reference": ref}), **{f"scene-{k}": s for k, s in enumerate(opened)},
                     **({"dem": dem_scene} if dem_scene is not None else {})}
            ingested = ingest_all(job, named, tile, c)
            ref = ref if virtual else ingested["reference"]
            opened = [ingested[f"scene-{k}"] for k in range(len(opened))]
            heights = None
            if dem_scene is not None:
                dem_scene = ingested["dem"]
                heights = MapDEM(job.file("dem.zarr"), scene_transform(dem_scene), tile)
        ref_reader = None if virtual else WindowReader(job.file("reference.zarr"))
        readers = [WindowReader(job.file(f"scene-{k}.zarr")) for k in range(len(opened))]
        shapes = [(s.sizes["y"], s.sizes["x"]) for s in opened]
        crs_wkt = ref.rio.crs.to_wkt() if ref.attrs.get("georeferenced") else None
        sensors = [None if s is None or crs_wkt is None else sensor_model("rpc" if isinstance(s, RPC) else "linescanner", s, crs_wkt)
                   for s in carried]
        ref_shape = (ref.sizes["y"], ref.sizes["x"])
        priors = [None if m is None else ref_to_scene_prior(m, m.initial_params(), transform, ref_shape, shapes[k], heights)
                  for k, m in enumerate(sensors)]
        threads = _threads(c)
        images, image_readers = [ref, *opened], [ref_reader, *readers]
        with timer("interest points"):
            first = 1 if virtual else 0  # a virtual reference has no image, no points
            points = scene_points(job, ["reference", *(f"scene-{k}" for k in range(len(opened)))][first:],
                                  images[first:], image_readers[first:], opts)
            points = [InterestPoints.concatenate([])] * first + points
        control, ref_to, to_ref, ref_tp = [], {}, {}, {}
        missed: dict[int, GeocoderError] = {}
        if virtual:  # placed by their georeferences; controlled by them unless the CSV controls the block
            for k, scene in enumerate(opened):
                if not scene.attrs.get("georeferenced"):  # placed by its neighbours, below
                    missed[k] = InputError(scene.attrs["source"], "has no georeference")
                    continue
                to_ref[k], ref_to[k] = georeference_mappings(scene, ref, order)
                if given is None and k in allowed:
                    control.append(georeference_control(k, scene, georeference_sigma))
            summary.georeference_sigma_px = None if given is not None else georeference_sigma
        with timer("control points"):
            found = [] if virtual else match_pairs(
                job, "control", [PairSpec(f"ref-{k}", 0, k + 1, priors[k]) for k in range(len(opened))], images,
                image_readers, points, opts)
            for k, result in enumerate(found):
                if isinstance(result, GeocoderError):
                    missed[k] = result
                    continue
                tp, mapping, _ = result
                tp = tp.select(tp.inlier)
                ref_tp[k] = tp
                ref_to[k] = mapping
                to_ref[k] = fit_polymap(tp.dist_x, tp.dist_y, tp.base_x, tp.base_y, order=order)
                if k in allowed:
                    ex, ny = pixel_to_world(transform, tp.base_x, tp.base_y)
                    control.append(Matches(-1, k, np.column_stack([ex, ny]), np.column_stack([tp.dist_x, tp.dist_y]),
                                           np.column_stack([tp.sigma_x, tp.sigma_y])))
        summary.control_points = [sum(len(m) for m in control if m.j == k) for k in range(len(opened))]
        if given is not None:  # the CSV's points: control observations as the reference's matches are
            control.extend(given.matches(len(opened)))
            summary.given_file = given.path
        placement = Placement()
        if missed and ref_to:
            with timer("placement by neighbours"):
                near_priors = [priors[k] if priors[k] is not None or not opts.use_georeference
                               else georeference_prior(ref, opened[k]) for k in range(len(opened))]
                placement = place_by_neighbours(job, images, image_readers, points, opts, shapes, to_ref, ref_to,
                                                near_priors)
        for k in range(len(opened)):
            if k in missed and k not in placement.via:
                summary.left_out[str(k)] = (f"{'placed by no georeference' if virtual else 'not found on the reference'} "
                                            f"({missed[k]}), nor on a placed scene ({placement.why_not(k)})")
        summary.placed = {str(k): ("georeference" if virtual else "reference") if k not in missed else
                          f"via scene {placement.via[k]}" if k in placement.via else "not placed"
                          for k in range(len(opened))}
        ties = []
        with timer("tie points"):
            placed = sorted(ref_to)
            overlaps = {(i, j): overlap_fraction(shapes[i], to_ref[i], ref_to[j], shapes[j])
                        for a, i in enumerate(placed) for j in placed[a + 1:]}
            pairs = [ij for ij, share in overlaps.items() if share >= 0.05]
            found = match_pairs(job, "ties", [PairSpec(f"pair-{i}-{j}", i + 1, j + 1,
                                                       affine_between(to_ref[i], ref_to[j], shapes[i])) for i, j in pairs],
                                images, image_readers, points, opts)
            for (i, j), result in zip(pairs, found):
                if isinstance(result, GeocoderError):
                    summary.pairs.append({"i": i, "j": j, "ties": 0, "overlap": round(overlaps[i, j], 3),
                                          "problem": str(result)})
                    continue
                tp, _, _ = result
                tp = tp.select(tp.inlier)
                ties.append(Matches(i, j, np.column_stack([tp.base_x, tp.base_y]), np.column_stack([tp.dist_x, tp.dist_y]),
                                    np.column_stack([tp.sigma_x, tp.sigma_y])))
                summary.pairs.append({"i": i, "j": j, "ties": len(tp), "overlap": round(overlaps[i, j], 3)})
        ok = connected_scenes(len(opened), control, ties, min_points=opts.min_tiepoints)
        ok &= np.array([k in to_ref for k in range(len(opened))], dtype=bool)  # CSV points do not place a scene
        for k in range(len(opened)):
            if not ok[k] and str(k) not in summary.left_out:
                summary.left_out[str(k)] = "tied to no control point (no overlap with a controlled scene)"
        block = [k for k in range(len(opened)) if ok[k]]
        if not block:
            raise InputError(reference or scenes[0], "no scene could be placed on the reference")
        index = {k: n for n, k in enumerate(block)}
        used, checks = _withhold(control, check_points)
        with timer("block adjustment"):
            def build():
                return build_problem(
                    [shapes[k] for k in block], [_to_map(to_ref[k], transform) for k in block],
                    [replace(m, j=index[m.j]) for m in used if m.j in index],
                    [Matches(index[t.i], index[t.j], t.a, t.b, t.sigma) for t in ties if t.i in index and t.j in index],
                    order=order, height=heights,
                    models=None if model == "polynomial" else [(sensors[k], sensors[k].initial_params()) for k in block],
                )

            problem = build()
            result = job.cached("adjustment", lambda: solve(problem, height=heights))
        summary.sigma0, summary.iterations = float(result.sigma0), int(result.iterations)
        points = point_table(problem, result, abs(transform.a))
        summary.rejected = {"robust": int((~result.obs_active).sum()) - int(result.n_snooped),
                            "snooping": int(result.n_snooped)}
        summary.point_sigma_px = _point_sigma(points)
        rays = np.bincount(np.bincount(problem.obs_point))
        summary.rays = {str(k): int(v) for k, v in enumerate(rays) if v and k}
        summary.rms_px = [float(np.sqrt(np.mean(np.sum(result.residuals[(problem.obs_frame == n) & result.obs_active] ** 2, 1))))
                          for n in range(len(block))]
        models = [(problem.frames[n].model, result.params[n]) for n in range(len(block))]
        if check_points:
            summary.check_points, summary.check_rmse_px = _check_residuals(checks, models, index, len(opened), heights)
        if given is not None:
            summary.given_points, summary.given_rmse_px = _check_residuals(
                [m for m in used if m.ground_sigma is not None], models, index, len(opened), heights)
            summary.given_residuals = _given_residuals(given, models, index, checks, heights)
        for n, k in enumerate(block):
            if k in placement.via:  # its footprint from its adjusted model, not the overlap's extrapolation
                to_ref[k], ref_to[k] = footprint_from_model(*models[n], transform, to_ref[k], shapes[k], heights)
        summary.block = list(block)
        nbands = opened[0].sizes["band"]
        gains = np.tile([1.0, 0.0], (len(block), nbands, 1))
        if balance:
            with timer("radiometric balance"):
                gains, summary.seam_step = _balance(
                    [readers[k] for k in block], ref_reader, transform, tile,
                    [] if virtual else [replace(m, j=index[m.j]) for m in control if m.j in index],
                    [Matches(index[t.i], index[t.j], t.a, t.b, t.sigma) for t in ties if t.i in index and t.j in index],
                    nbands)
        ds, grid, out_transform, out_grid = _output_grid(ref, [to_ref[k] for k in block], [shapes[k] for k in block],
                                                         output_tile, opened[0].sizes["band"], heights=heights is not None,
                                                         resolution=resolution, crs=crs)
        summary.shape = (ds.sizes["y"], ds.sizes["x"])
        ds.attrs.update(_attrs(summary, block, models, gains))
        store = job.file("output.zarr")
        if not job.done("output-created"):
            ds.to_zarr(store, mode="w", zarr_format=3, consolidated=False, compute=False)
            job.save("output-created")
        xr.Dataset({name: ("point", points[:, k]) for k, name in enumerate(POINT_COLUMNS)},
                   attrs={"long_name": "adjusted ground points (geocoder.mosaic.block.point_table)",
                          "units": "x, y: map units of the reference's CRS; sigma_x, sigma_y: reference pixels"}
                   ).to_zarr(store, group="points", mode="w", zarr_format=3, consolidated=False)
        fields: list = [None] * len(block)
        if dense:
            with timer("dense refinement"):
                todo = [n for n, k in enumerate(block) if k in allowed and k in ref_tp]
                done = _concurrently(
                    lambda n: refine_scene(job, key, store, n, ref, ref_reader, readers[block[n]], models[n], ref_tp[block[n]],
                                      to_ref[block[n]], shapes[block[n]], transform, opts, heights),
                    todo, "dense refinement (scenes)", threads)
                for n, f in zip(todo, done):
                    fields[n] = f
                # then the scenes without control (or whose refinement failed), against their refined neighbours
                via = {} if dense == "control" else refine_by_neighbours(
                    job, key, store, ref, transform, [readers[k] for k in block], models, [shapes[k] for k in block],
                    [to_ref[k] for k in block], fields, gains,
                    [Matches(index[t.i], index[t.j], t.a, t.b, t.sigma) for t in ties if t.i in index and t.j in index],
                    opts, lambda fn, items, phase: _concurrently(fn, items, phase, threads), heights)
                summary.dense_refined = [
                    "via " + ", ".join(str(block[k]) for k in via[n]) if n in via else "reference" if fields[n] else "not"
                    for n in range(len(block))]
        if resolution is None and crs is None:  # the reference's grid: output pixel = reference pixel - origin
            origin = tuple(int(round(v)) for v in ~transform * (out_transform.c, out_transform.f))  # output (0, 0) in reference pixels
            to_out = [_shifted(to_ref[k], origin) for k in block]
            boxes = np.array([_footprint_box(to_ref[k], shapes[k], origin) for k in block])
        else:  # output pixels reach the dense fields through the map and the reference's transform
            origin = transform
            to_out = [_through_map(to_ref[k], transform, out_grid) for k in block]
            boxes = np.array([_footprint_box(f, shapes[k], (0, 0)) for f, k in zip(to_out, block)])
        summary.footprints = [footprint_outline(f, shapes[k]) for f, k in zip(to_out, block)]
        _adjustment_figures(summary, problem, result, models, [shapes[k] for k in block],
                            [_to_map(to_ref[k], transform) for k in block], to_out, heights)
        grid_shape = (ds.sizes["y"], ds.sizes["x"])
        plan = None
        block_pairs = [(index[p["i"]], index[p["j"]]) for p in summary.pairs
                       if p["i"] in index and p["j"] in index and p["ties"] > 0]
        if seams == "least-cost":
            with timer("seams"):
                plan = plan_seams(job, store, grid_shape, output_tile, out_grid, models, [readers[k] for k in block],
                                  [shapes[k] for k in block], gains, boxes, block_pairs, dem=heights)
                summary.seam_cells_moved = plan.pop("changed")
        covs, unmodelled = scene_uncertainty(problem, result, len(block))
        with timer("mosaic"):
            tasks = {t.key: dask.delayed(_mosaic_tile, pure=True)(
                store, (t.row0, t.row1, t.col0, t.col1), out_grid, models, [readers[k] for k in block],
                [shapes[k] for k in block], feather, resampling, gains, fields, origin, boxes, plan, grid_shape, heights,
                covs, unmodelled)
                for t in grid}
            done = job.run_tiles("mosaic", tasks, phase="mosaic tiles")
        _seam_figures(summary, [d["seams"] for d in done.values()], block, problem, result)
        summary.job = job.report()
        import zarr

        zarr.open_group(store, mode="r+").attrs.update({
            **_attrs(summary, block, models, gains),
            "dense_fields": json.dumps([None if f is None else {"group": f["group"], "row0": f["row0"], "col0": f["col0"],
                                                                "shape": list(f["shape"])} for n, f in enumerate(fields)]),
            **({"reference_origin": json.dumps(list(origin))} if not isinstance(origin, Affine) else
               {"reference_transform": json.dumps(list(origin)[:6])}),
            **({"models_crs": out_grid.ref_crs} if isinstance(out_grid, Reprojected) else {}),
        })
        if cog is not None:
            with timer("cog"):
                to_cog(store, cog, variable="mosaic", client=c, blocksize=output_tile,
                       overwrite=overwrite)
        if out is None:
            result_ds = xr.open_zarr(store, decode_coords="all", consolidated=False).load()
        else:
            write_overviews(store, client=c)
            commit_output(store, out, overwrite=overwrite)
    if out is not None:
        result_ds = xr.open_zarr(out, decode_coords="all", consolidated=False)
    if report is not None:
        from .report import write_report

        write_report(out if out is not None else result_ds, report, overwrite=overwrite)
    return result_ds


def sample_points(reader: WindowReader, x: np.ndarray, y: np.ndarray, tile: int, *, radius: int = 3) -> np.ndarray:
    """Mean values ``(band, n)`` of a scene over ``(2 radius + 1)^2`` px around scattered points.

    A window mean, not the value at the point: tie points sit on corners, where the two
    scenes' different resampling blur changes single values but hardly a window's mean. One
    small window is read per tile of points.
    """
    off = np.arange(-radius, radius + 1, dtype=np.float64)
    ox, oy = np.meshgrid(off, off)
    out = np.full((reader.shape[0], x.size), np.nan, dtype=np.float32)
    ok = np.isfinite(x) & np.isfinite(y)
    key = np.where(ok, (np.floor(y / tile) * 1e6 + np.floor(x / tile)), -1)
    for k in np.unique(key[ok]):
        sel = key == k
        v = reader.sample(x[sel, None, None] + ox, y[sel, None, None] + oy, method="bilinear")
        with np.errstate(invalid="ignore"):
            out[:, sel] = np.mean(v, axis=(-2, -1))  # NaN if the window leaves the scene
    return out


def _balance(readers: list, ref_reader: WindowReader | None, transform: Affine, tile: int, control: list, ties: list,
             nbands: int):
    """Gain and offset per scene and band (``(K, B, 2)``) and the seam step before and after
    (without a reference, ``ref_reader`` None and no ``control``: the scenes among themselves)."""
    ref_bands = nbands if ref_reader is None else ref_reader.shape[0]
    cvals = []
    for m in control:
        rx, ry = world_to_pixel(transform, m.a[:, 0], m.a[:, 1])
        cvals.append((m.j, sample_points(readers[m.j], m.b[:, 0], m.b[:, 1], tile), sample_points(ref_reader, rx, ry, tile)))
    tvals = [(t.i, t.j, sample_points(readers[t.i], t.a[:, 0], t.a[:, 1], tile),
              sample_points(readers[t.j], t.b[:, 0], t.b[:, 1], tile)) for t in ties]
    gains = np.zeros((len(readers), nbands, 2))
    before, after = [], []
    for b in range(nbands):
        rb = b if b < ref_bands else 0
        c = [(k, v[b], r[rb]) for k, v, r in cvals] if ref_bands == nbands else []  # else: scenes among themselves
        t = [(i, j, vi[b], vj[b]) for i, j, vi, vj in tvals]
        gains[:, b] = solve_balance(len(readers), c, t)
        before.append(seam_step(t))
        after.append(seam_step(t, gains[:, b]))
    return gains, [float(np.sqrt(np.nanmean(np.square(before)))), float(np.sqrt(np.nanmean(np.square(after))))]


def _given_residuals(given, models: list, index: dict, checks: list, heights=None) -> list[list]:
    """Every point of the ``control`` CSV: ``[id, scene, residual px, role]``, the residual its
    scene pixel leaves against its map position through the adjusted model (None for a scene
    out of the block), role ``"control"`` or ``"check"`` (withheld from the adjustment)."""
    withheld = {(m.j, float(x), float(y)) for m in checks if m.ground_sigma is not None for x, y in m.b}
    out = []
    for i in range(len(given)):
        k = int(given.scene[i])
        col, row = (float(v) for v in given.pixel[i])
        role = "check" if (k, col, row) in withheld else "control"
        if k not in index:
            out.append([given.ids[i], k, None, role])
            continue
        residual = _pixel_residuals(models[index[k]], given.world[i : i + 1], given.pixel[i : i + 1], heights)[0]
        out.append([given.ids[i], k, round(float(residual), 4), role])
    return out


def _pixel_residuals(model: tuple, world: np.ndarray, pixel: np.ndarray, heights=None) -> np.ndarray:
    """Distance (scene px) between measured ``pixel`` (n, 2) and where the adjusted ``model``
    (``(model, params)``) puts the map points ``world`` (n, 2), at the DEM's heights (0 without)."""
    e, n = world[:, 0], world[:, 1]
    h = np.zeros(e.size) if heights is None else np.asarray(heights(e, n), dtype=np.float64)
    xy = model[0].project(model[1], np.column_stack([e, n, h]))
    return np.hypot(*(xy - pixel).T)


def _withhold(control: list, share: float) -> tuple[list, list]:
    """``control`` split into the points the adjustment uses and every n-th withheld as a check
    (``n = round(1 / share)``; none for ``share = 0``)."""
    if not share:
        return control, []
    n = max(round(1.0 / share), 2)
    used, checks = [], []
    for m in control:
        keep = np.arange(len(m)) % n != n - 1
        for part, sel in ((used, keep), (checks, ~keep)):
            part.append(replace(m, a=m.a[sel], b=m.b[sel], sigma=m.sigma[sel],
                                ground_sigma=None if m.ground_sigma is None else m.ground_sigma[sel]))
    return used, checks


def _check_residuals(checks: list, models: list, index: dict, nscenes: int, heights=None) -> tuple[list, list]:
    """Check points per scene and the RMS of their residuals (scene pixels) through the adjusted models."""
    count = [0] * nscenes
    rmse = [float("nan")] * nscenes
    for m in checks:
        if m.j not in index or len(m) == 0:
            continue
        count[m.j] = len(m)
        rmse[m.j] = float(np.sqrt(np.mean(_pixel_residuals(models[index[m.j]], m.a, m.b, heights) ** 2)))
    return count, rmse


def _footprint_box(to_ref, shape: tuple[int, int], origin: tuple[int, int], margin: int = 16) -> tuple[int, int, int, int]:
    """``row0, row1, col0, col1`` (output pixels) around a scene's footprint, grown by ``margin``.

    ``to_ref``: scene pixel -> reference pixel, ``origin`` the output's pixel (0, 0) there; or
    scene pixel -> output pixel directly, with ``origin = (0, 0)``."""
    h, w = shape
    t = np.linspace(0.0, 1.0, 17)
    xs = np.concatenate([t * (w - 1), np.full(17, w - 1.0), t * (w - 1), np.zeros(17)])
    ys = np.concatenate([np.zeros(17), t * (h - 1), np.full(17, h - 1.0), t * (h - 1)])
    rx, ry = to_ref(xs, ys)
    return (int(np.floor(ry.min())) - origin[1] - margin, int(np.ceil(ry.max())) - origin[1] + margin + 1,
            int(np.floor(rx.min())) - origin[0] - margin, int(np.ceil(rx.max())) - origin[0] + margin + 1)


def scene_positions(ds: xr.Dataset, store: str | os.PathLike) -> list[tuple[np.ndarray, np.ndarray]]:
    """Where every output pixel lies in each block scene (the positions the mosaic sampled).

    Parameters
    ----------
    ds : xarray.Dataset
        A mosaic (:func:`mosaic`).
    store : str or PathLike
        The mosaic's store (its ``dense/<n>`` groups hold the refined fields).

    Returns
    -------
    list of tuple of ndarray
        Per scene (``attrs["scenes"]`` order), the column and row of every output pixel in
        the scene: from its adjusted model (at the ``height`` layer's heights, if the
        mosaic has one), or from its dense field where it was refined.
    """
    models = load_models(ds)
    fields = json.loads(ds.attrs.get("dense_fields", "null")) or [None] * len(models)
    transform = ds.rio.transform()
    if "models_crs" in ds.attrs:  # another CRS than the models': its pixels mapped to theirs
        transform = Reprojected(transform, ds.rio.crs.to_wkt(), ds.attrs["models_crs"])
    ref = (Affine(*json.loads(ds.attrs["reference_transform"])) if "reference_transform" in ds.attrs
           else tuple(json.loads(ds.attrs.get("reference_origin", "[0, 0]"))))
    window = (0, ds.sizes["y"], 0, ds.sizes["x"])
    heights = np.asarray(ds["height"].values, dtype=np.float64) if "height" in ds else None
    out = []
    for (model, params), f in zip(models, fields):
        if f is not None:
            f = {**f, "store": f"{os.fspath(store)}/{f['group']}"}
        out.append(_scene_xy(model, params, transform, window, f, ref, heights))
    return out


def _threads(client) -> int:
    """Pairs matched at once: enough small graphs in flight to keep every worker thread busy."""
    return max(2, min(16, 2 * sum(client.nthreads().values())))


def _concurrently(fn, items: list, phase: str, threads: int) -> list:
    """``fn(item)`` for every item, ``threads`` at a time, results in the order of ``items``.

    Every call submits its own small tile graphs; running several at once from client
    threads keeps the cluster busy where one pair of small scenes has fewer tiles than there
    are workers, and overlaps one pair's client-side work with the others' tasks. The
    progress shows one unit per item (the calls' own phases are not shown).
    """
    def quiet(item):
        with progress.reporting(False):
            return fn(item)

    bar = progress.current()
    bar.phase(phase, len(items))
    pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="geocoder-pairs")
    try:
        futures = [pool.submit(contextvars.copy_context().run, quiet, item) for item in items]
        for _ in as_completed(futures):
            bar.advance()
        results = [f.result() for f in futures]
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown()
    bar.close()
    return results


def _output_grid(ref: xr.DataArray, to_ref: list, shapes: list, tile: int, nbands: int, heights: bool = False,
                 resolution: float | None = None, crs: str | None = None):
    """Empty output dataset covering every scene's footprint: on the reference's pixel grid, or
    (``resolution``, ``crs``: WKT) on that grid (:func:`~geocoder.mosaic.outgrid.other_grid`).

    Returns the dataset, its tiles, its transform and the grid :func:`~geocoder.mosaic.outgrid.to_map` takes.
    """
    corners = []
    for f, (h, w) in zip(to_ref, shapes):
        t = np.linspace(0, 1, 17)
        xs = np.concatenate([t * (w - 1), np.full(17, w - 1.0), t * (w - 1), np.zeros(17)])
        ys = np.concatenate([np.zeros(17), t * (h - 1), np.full(17, h - 1.0), t * (h - 1)])
        corners.append(np.column_stack(f(xs, ys)))
    pts = np.concatenate(corners)
    out_crs = ref.rio.crs if ref.attrs.get("georeferenced") else None
    if resolution is None and crs is None:
        c0, r0 = np.floor(pts.min(axis=0)).astype(int)
        c1, r1 = np.ceil(pts.max(axis=0)).astype(int) + 1
        transform = (scene_transform(ref) or Affine.identity()) * Affine.translation(c0, r0)
        height, width = int(r1 - r0), int(c1 - c0)
        grid_map = transform
    else:
        ref_transform = scene_transform(ref)
        e, n = pixel_to_world(ref_transform, pts[:, 0], pts[:, 1])
        transform, (height, width), grid_map = other_grid(ref_transform, ref.rio.crs.to_wkt(), e, n,
                                                          resolution=resolution, crs=crs)
        out_crs = crs or out_crs
    grid = TileGrid.regular(height, width, tile)
    chunks = ((nbands,), *(tuple(min(tile, n - i) for i in range(0, n, tile)) for n in (height, width)))
    xs, _ = pixel_to_world(transform, np.arange(width), np.zeros(width))
    _, ys = pixel_to_world(transform, np.zeros(height), np.arange(height))
    ds = xr.Dataset(
        {
            "mosaic": (("band", "y", "x"), da.full((nbands, height, width), np.nan, dtype=np.float32, chunks=chunks)),
            "source": (("y", "x"), da.full((height, width), NO_SOURCE, dtype=np.uint16, chunks=chunks[1:]),
                       {"long_name": "index of the scene each pixel comes from (attrs scenes)", "_FillValue_meaning": "65535: none"}),
        },
        coords={"band": np.arange(1, nbands + 1), "y": ys, "x": xs},
    )
    ds["mosaic"].attrs["long_name"] = "mosaic of the block's scenes"
    if heights:
        ds["height"] = (("y", "x"), da.full((height, width), np.nan, dtype=np.float32, chunks=chunks[1:]),
                        {"long_name": "ground height of the pixel (the DEM's, bilinear)", "units": "m"})
    ds["status"] = (("y", "x"), da.zeros((height, width), dtype=np.uint8, chunks=chunks[1:]), {
        **status_attrs(), "long_name": "what the pixel's position in its source scene rests on",
        "comment": "matched, filled: the position in the source scene is its dense field's (--dense; matched, or "
                   "filled along the row); blunder, no_texture: the dense matcher rejected the pixel or found too "
                   "little texture, and model: no dense field there; the position is the scene's adjusted model's; "
                   "outside: no scene covers the pixel"})
    for name, axis in (("sigma_x", "columns (x)"), ("sigma_y", "rows (y)")):
        ds[name] = (("y", "x"), da.full((height, width), np.nan, dtype=np.float32, chunks=chunks[1:]), {
            "long_name": f"standard deviation of the pixel's position along the output's {axis}",
            "units": "pixel",
            "comment": "of the position in the source scene (a feathered pixel: the scene source names): the "
                       "dense match's sigma where matched; elsewhere the block adjustment's parameter covariance "
                       "(with sigma0 taken as at least 1) propagated to the pixel, plus the scene's mean squared "
                       "residual; NaN where unknown (no covariance; a pixel matched by a scene refined against its neighbours, "
                       "whose error the match leaves out) or no scene covers the pixel "
                       "(geocoder.mosaic.layers)"})
    if out_crs is not None:
        ds = georeference(ds, out_crs, transform)
    return ds, grid, transform, grid_map


def _attrs(summary: MosaicSummary, block: list[int], models: list, gains: np.ndarray) -> dict:
    from dataclasses import asdict

    return {
        "radiometry": json.dumps(np.asarray(gains).tolist()),
        "scenes": json.dumps([summary.scenes[k] for k in block]),
        "models": json.dumps([model_to_dict(m, p) for m, p in models]),
        "summary": json.dumps(asdict(summary), default=float),
        **product_attrs("mosaic"),
    }


def load_models(ds: xr.Dataset) -> list:
    """The adjusted per-scene models of a mosaic.

    Parameters
    ----------
    ds : xarray.Dataset
        A mosaic (:func:`mosaic`).

    Returns
    -------
    list of tuple
        ``(model, params)`` per scene, in ``attrs["scenes"]`` order: a
        :class:`~geocoder.adjust.models.MapPolynomial`, or a
        :class:`~geocoder.mosaic.sensors.MapGround` line scanner or RPC; all map ground
        ``(E, N, h)`` of the reference's CRS to scene pixels: the mosaic's, or, for a mosaic
        written in another (``crs=``), the one ``attrs["models_crs"]`` holds (WKT).
    """
    return [model_from_dict(m) for m in json.loads(ds.attrs["models"])]


def _carried(path) -> object | None:
    """The RPC or line scanner a scene carries, if any (its footprint for a polynomial block)."""
    for kind in ("rpc", "linescanner"):
        try:
            return scene_sensor(path, kind)
        except (InputError, OSError, ValueError):
            continue
    return None


def _open_dem(path, ref: xr.DataArray, tile: int) -> xr.DataArray:
    """The DEM as a scene in the reference's CRS (reprojected, bilinear, if it has another)."""
    dem = open_scene(path, chunks=tile, grid=True)
    if not dem.attrs.get("georeferenced"):
        raise InputError(path, "the DEM is not georeferenced")
    if not ref.attrs.get("georeferenced"):
        raise InputError(ref.attrs["source"], "is not georeferenced: a DEM needs the reference's CRS")
    if dem.rio.crs != ref.rio.crs:
        from rasterio.enums import Resampling

        attrs = dict(dem.attrs)
        dem = dem.isel(band=[0]).load().rio.reproject(ref.rio.crs, resampling=Resampling.bilinear).chunk(
            {"band": 1, "y": tile, "x": tile})
        dem.attrs.update(attrs)
    return dem.isel(band=[0])


def world_grid(ds: xr.Dataset) -> tuple[np.ndarray, np.ndarray]:
    """Map coordinates of every output pixel centre (from the store's x/y coordinates)."""
    return np.meshgrid(ds.x.values, ds.y.values)


__all__ = ["MosaicSummary", "load_models", "mosaic", "scene_positions", "world_grid"]
