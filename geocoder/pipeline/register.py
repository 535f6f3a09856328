"""``register(base, distorted)``: the end-to-end polynomial registration job.

Ingest both scenes to Zarr, align coarsely, find interest points and tie points tile by
tile, fit a robust global polynomial on one node, then resample the original distorted
image once onto the base grid, writing everything to one Zarr store atomically.

The module is over 500 lines because it is the job's driver: :func:`find_tiepoints` and
:func:`register` call the stages in order (their graphs live in :mod:`.detect`,
:mod:`.correspond`, :mod:`.dense`, :mod:`.lines` and :mod:`.resample`), with the input checks,
the resume points and the output's layout beside them.
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from typing import Any

import dask
import dask.array as da
import numpy as np
import xarray as xr
from dask.delayed import Delayed

from .. import progress, storage
from ..conventions import georeference, pixel_grid, status_attrs
from ..errors import InputError, MatchingError
from ..kernels.figures import chunk_figures, combine_figures
from ..kernels.interest import InterestPoints
from ..kernels.polynomial import PolyMap, exponents
from ..match.coarse import CoarseAlignment
from ..match.correspondence import CorrespondenceOptions
from ..match.tiepoints import TiePoints
from ..multiscales import OverviewPlan, plan_overviews
from ..options import default_tile, get_option
from ..outputs import check_output, commit_output, product_attrs
from ..progress import Progress
from ..quality.lines import LineOptions
from ..quality.postfilter import PostFilterOptions
from ..runtime import dask_client
from ..scene import WindowReader, ingest_scenes, open_scene
from ..status import Status
from ..tiles import TileGrid
from .bands import Bands
from .coarse import overview_factor, submit_coarse_alignment
from .correspond import first_pass, fit_global, match_tiles
from .dense import DenseOptions, dense_field, grow_tiles, seeds_from_tiepoints
from .detect import InterestOptions, interest_points_many
from .job import Job, JobRun, fingerprint, input_identity
from .lines import line_field, row_corrections
from .resample import model_status, polynomial_displacement, resample

log = logging.getLogger("geocoder")

RESAMPLING = ("nearest", "bilinear", "cubic", "lanczos")
LONG_NAMES = {
    "sigma_x": "standard deviation of dx from the least-squares match",
    "sigma_y": "standard deviation of dy from the least-squares match",
    "correlation": "correlation coefficient of the least-squares match",
}


@dataclass(frozen=True)
class RegisterOptions:
    """Everything :func:`register` can be told, with the seed's defaults.

    Attributes
    ----------
    tile : int or None
        Tile (chunk) size of every tile-parallel stage, a multiple of 64; None:
        :func:`geocoder.get_option` ``("tile")`` (512 unless set; :func:`register` takes 1024 for a
        base scene of 2048 px and more, :func:`geocoder.options.default_tile`).
    resampling : {"nearest", "bilinear", "cubic", "lanczos"}
        Interpolator of the single resampling.
    band, dist_band : int
        1-based band matched in the base and the distorted scene (``dist_band`` None: ``band``).
    bands : tuple of int
        1-based bands the dense matching uses at once (seed 003 sec. 11, the multispectral
        Otto-Chau): one geometry and a gain and offset per band in one least-squares system,
        so a patch without texture in one band matches on the others. The same bands of both
        scenes, co-registered within each; each band weighs by its grey values scaled to unit
        noise over the whole scene. Empty: ``band`` alone. The coarse alignment, interest points
        and tie points use ``band``. Needs ``dense``.
    order : int
        Order of the global polynomial (2: the seed's quadratic).
    passes : int
        Correspondence passes (the later ones match every base point from the fitted polynomial).
    min_tiepoints : int
        Fewest tie points a registration accepts.
    interest : InterestOptions
        The Foerstner interest operator.
    correspondence : CorrespondenceOptions
        Matching of the interest points (robust correspondence).
    use_georeference : bool
        Start the coarse alignment from the scenes' georeferences when both have one.
    dense : bool
        Match every pixel (False: stop at the global polynomial).
    matching : DenseOptions
        The dense matching (region growing, halo exchange).
    postfilter : PostFilterOptions
        The scan-line post-filter of the dense field.
    lines : LineOptions
        The per-line estimates of the unmatched pixels (:mod:`geocoder.quality.lines`).
    """

    tile: int | None = None
    resampling: str = "bilinear"
    band: int = 1
    dist_band: int | None = None
    bands: tuple[int, ...] = ()
    order: int = 2
    passes: int = 2
    min_tiepoints: int = 12
    interest: InterestOptions = field(default_factory=InterestOptions)
    correspondence: CorrespondenceOptions = field(default_factory=CorrespondenceOptions)
    use_georeference: bool = True
    dense: bool = True
    matching: DenseOptions = field(default_factory=DenseOptions)
    postfilter: PostFilterOptions = field(default_factory=PostFilterOptions)
    lines: LineOptions = field(default_factory=LineOptions)

    def validate(self) -> None:
        """Check every option; raise ValueError naming the first that is out of range."""
        if self.tile is None:
            return replace(self, tile=get_option("tile")).validate()
        if self.resampling not in RESAMPLING:
            raise ValueError(f"resampling must be one of {RESAMPLING}, got {self.resampling!r}")
        if self.tile < 64 or self.tile % self.interest.cell:
            raise ValueError(f"tile must be a multiple of {self.interest.cell} and >= 64, got {self.tile}")
        if not 1 <= self.order <= 3:
            raise ValueError(f"order must be 1, 2 or 3, got {self.order}")
        if self.bands:
            if len(self.bands) < 2 or len(set(self.bands)) != len(self.bands) or min(self.bands) < 1:
                raise ValueError(f"bands must be two or more distinct 1-based bands, got {self.bands!r}")
            if self.dist_band is not None:
                raise ValueError("bands match the same bands of both scenes: dist_band cannot be set with them")
            if not self.dense:
                raise ValueError("bands are matched together by the dense stage: they need dense matching (not --no-dense)")
            if self.matching.col_step > 1 and self.matching.densify != "field":
                raise ValueError("matching several bands needs the dense stage's densify='field'")
        self.lines.validate()


@dataclass
class RegisterSummary:
    """What the CLI prints and the store keeps in its attributes."""

    base: str
    distorted: str
    base_points: int = 0
    distorted_points: int = 0
    tiepoints: int = 0
    inliers: int = 0
    rms: float = float("nan")
    sigma0: float = float("nan")
    coarse_method: str = ""
    pass_tiepoints: list = field(default_factory=list)
    dense_rounds: int = 0
    dense_converged: bool = True
    dense_new_per_round: list = field(default_factory=list)
    status_counts: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)
    job: dict = field(default_factory=dict)

    def lines(self) -> list[str]:
        total = sum(self.seconds.values())
        return [
            f"interest points: base {self.base_points}, distorted {self.distorted_points}",
            f"tie points: {self.tiepoints} ({self.inliers} kept by the robust polynomial; per pass {self.pass_tiepoints})",
            f"robust RMS of tie-point residuals: {self.rms:.3f} px (sigma0 {self.sigma0:.3f} px)",
            f"coarse alignment: {self.coarse_method}",
            *(
                [f"dense matching: {self.dense_rounds} round(s) of halo exchange"
                 f"{'' if self.dense_converged else ' (round limit reached)'}, new matches per round {self.dense_new_per_round}"]
                if self.dense_rounds else []
            ),
            *(["pixels: " + ", ".join(f"{k} {v}" for k, v in self.status_counts.items())] if self.status_counts else []),
            *([f"resumed: {self.job['skipped']} of {self.job['tile_tasks']} tile tasks finished earlier, "
                f"at most {self.job['recomputed']} ({self.job['recomputed_fraction']:.1%}) computed again"] if self.job.get("resumed") else []),
            f"time: {total:.1f} s (" + ", ".join(f"{k} {v:.1f}" for k, v in self.seconds.items()) + ")",
        ]


class _Timer:
    def __init__(self, summary: RegisterSummary) -> None:
        self.summary = summary

    def __call__(self, name: str):
        timer = self

        class _Span:
            def __enter__(self):
                self.t = time.perf_counter()
                log.info("%s ...", name)

            def __exit__(self, *exc):
                timer.summary.seconds[name] = time.perf_counter() - self.t

        return _Span()


def _check_overlap(predict: PolyMap, base_shape, dist_shape, base_name: str, dist_name: str) -> None:
    h, w = base_shape
    ys, xs = np.mgrid[0 : h : max(h // 32, 1), 0 : w : max(w // 32, 1)]
    px, py = predict(xs.astype(float), ys.astype(float))
    inside = (px >= 0) & (px <= dist_shape[1] - 1) & (py >= 0) & (py <= dist_shape[0] - 1)
    if inside.mean() < 0.01:
        raise InputError(dist_name, f"does not overlap the base image {base_name}")


def _tiepoint_dataset(tp: TiePoints) -> xr.Dataset:
    return xr.Dataset({k: ("point", v) for k, v in tp.columns().items()})


def find_tiepoints(
    base: xr.DataArray,
    dist: xr.DataArray,
    base_reader: WindowReader,
    dist_reader: WindowReader,
    opts: RegisterOptions,
    summary: RegisterSummary,
    timer,
    job: Job | None = None,
    prior: np.ndarray | None = None,
    points: tuple[InterestPoints, InterestPoints] | None = None,
    overviews: tuple[np.ndarray, np.ndarray] | None = None,
    grid: TileGrid | None = None,
) -> tuple[TiePoints, PolyMap, CoarseAlignment]:
    """Coarse alignment, interest points and correspondence passes; gathered tie points.

    ``prior`` (2x3 affine base pixel -> distorted pixel) replaces the georeference as the
    start of the coarse alignment; ``points`` are the interest points of both scenes when
    they are known already (a scene in several pairs is searched once); ``overviews`` those
    the coarse alignment runs on, when made already (see
    :func:`geocoder.pipeline.coarse.submit_coarse_alignment`); ``grid`` the job's tiles
    (default: the base's chunks).
    """
    def cached(stage, make):
        return make() if job is None else job.cached(stage, make)

    band = opts.band - 1
    dband = (opts.dist_band or opts.band) - 1
    # the coarse alignment (one task) runs on the cluster while the interest points are found;
    # its stage time is what is left of it after them
    pending = None
    if job is None or not job.done("coarse"):
        pending = submit_coarse_alignment(base, dist, band=band, dist_band=dband,
                                          use_georeference=opts.use_georeference, prior=prior, overviews=overviews)
    try:
        with timer("interest points"):
            if points is None:
                bpts, dpts = interest_points_many([base.data[band], dist.data[dband]], opts.interest, job=job,
                                                  names=["base", "distorted"], readers=[base_reader, dist_reader],
                                                  bands=[band, dband])
            else:
                bpts, dpts = points
        with timer("coarse alignment"):
            coarse = cached("coarse", lambda: pending.result())  # pending is None when cached
    except BaseException:
        if pending is not None:
            pending.cancel()  # never raises: the error that got here is the one to report
        raise
    summary.coarse_method = f"{coarse.method} (pyramid 1/{coarse.factor}, peak {coarse.peak:.2f})"
    base_shape = (base.sizes["y"], base.sizes["x"])
    dist_shape = (dist.sizes["y"], dist.sizes["x"])
    _check_overlap(coarse.mapping, base_shape, dist_shape, base.attrs["source"], dist.attrs["source"])
    summary.base_points, summary.distorted_points = len(bpts), len(dpts)
    for pts, scene in ((bpts, base), (dpts, dist)):
        if len(pts) < opts.min_tiepoints:
            raise InputError(scene.attrs["source"], f"has too little texture: {len(pts)} interest points found")
    grid = grid or TileGrid.from_chunks(base.data.chunks[1:])
    predict = coarse.mapping
    copts = opts.correspondence
    tp, mapping = TiePoints.empty(), predict
    with timer("correspondence"):
        # pass 1: pairs of interest points (seed 000 sec. 4.4); if the images defeat it but
        # the coarse alignment is a full affine, match from the coarse prediction instead.
        # When guided passes follow, pass 1's polynomial only predicts where they refine every
        # base point, so on a scene with many points its pairs stay where the interest points
        # put them (a third of the correspondence's work; the tie points are the later passes')
        match = partial(match_tiles, base_reader, dist_reader, grid, band=band, dist_band=dband, opts=copts, job=job)

        def too_few(found: TiePoints) -> MatchingError:
            return MatchingError(f"only {len(found)} tie points found between {base.attrs['source']} and "
                                 f"{dist.attrs['source']}")

        # unrefined, on a large scene pass 1 pairs the strongest base point of every 64-px square
        first, refined = first_pass(bpts, predict, dist_shape, order=opts.order, passes=opts.passes)
        found, _ = match(first, dpts, predict, refine=refined, stage="correspondence (pass 1)")
        summary.pass_tiepoints.append(len(found))
        if len(found) < opts.min_tiepoints and coarse.affine:
            found, _ = match(bpts, dpts, predict, guided=True, stage="correspondence (pass 1, guided)")
            summary.pass_tiepoints.append(len(found))
            refined = True
        if len(found) < opts.min_tiepoints:
            raise too_few(found)
        tp, mapping = fit_global(found, order=opts.order)
        # later passes: every base point matched from the fitted polynomial
        for i in range(1, opts.passes):
            found, _ = match(bpts, dpts, mapping, guided=True, stage=f"correspondence (pass {i + 1})")
            summary.pass_tiepoints.append(len(found))
            if len(found) < opts.min_tiepoints:
                break
            tp, mapping = fit_global(found, order=opts.order)
            refined = True
        if not refined:  # no guided pass found enough: pass 1's pairs refined, as the tie points
            found, _ = match(bpts, dpts, predict, stage="correspondence (pass 1, refined)")
            summary.pass_tiepoints.append(len(found))
            if len(found) < opts.min_tiepoints:
                raise too_few(found)
            tp, mapping = fit_global(found, order=opts.order)
    summary.tiepoints = len(tp)
    summary.inliers = int(tp.inlier.sum())
    res = np.hypot(tp.residual_x, tp.residual_y)[tp.inlier]
    summary.rms = float(np.sqrt(np.mean(res**2))) if res.size else float("nan")
    summary.sigma0 = float(mapping.fit_info.sigma0) if mapping.fit_info is not None else float("nan")
    return tp, mapping, coarse


def register(
    base,
    distorted,
    *,
    out: str | os.PathLike | None = None,
    resampling: str | None = None,
    tile: int | None = None,
    client=None,
    scheduler: str | None = None,
    band: int | None = None,
    dist_band: int | None = None,
    bands: tuple[int, ...] | None = None,
    order: int | None = None,
    dense: bool | None = None,
    nodata: float | None = None,
    dist_nodata: float | None = None,
    options: RegisterOptions | None = None,
    resume: bool = True,
    overwrite: bool = False,
    show_progress: Progress | bool | None = None,
    via=None,
) -> xr.Dataset:
    """Register ``distorted`` onto the grid of ``base``.

    Parameters
    ----------
    base, distorted : str, PathLike or xarray.DataArray
        GeoTIFF/COG/Zarr paths (or scenes from :func:`geocoder.open_scene`).
    out : str or PathLike, optional
        Zarr store to write: a local path or any fsspec URL (``s3://bucket/scene.zarr``),
        committed atomically. The job's working files live beside it (see
        :func:`job_directory`). Without it the result is computed into memory.
    resampling : {"nearest", "bilinear", "cubic", "lanczos"}
        Interpolator of the single resampling.
    tile : int, optional
        Tile size (chunk) of all tile-parallel stages; a multiple of 64. Default
        ``options.tile``, else the option ``tile`` if :func:`geocoder.set_options` or Dask
        config ``geocoder.tile`` sets it, else 512, or 1024 for a base scene of 2048 px and more
        on its smaller side (:func:`geocoder.options.default_tile`).
    client : distributed.Client, optional
        Where to run; default ``scheduler`` or ``DASK_SCHEDULER_ADDRESS``, else a local cluster.
    scheduler : str, optional
        Address of a Dask scheduler (or the ``cluster.json`` of ``geocoder cluster up``) to
        connect to when no ``client`` is given.
    band, dist_band : int
        1-based band used for matching (``dist_band`` defaults to ``band``).
    bands : sequence of int, optional
        1-based bands the dense matching uses at once (:attr:`RegisterOptions.bands`).
    order : int
        Order of the global polynomial (2 = the seed's quadratic).
    dense : bool
        Match every pixel (region-growing least squares with halo exchange, scan-line
        post-filter); False stops at the global polynomial.
    nodata, dist_nodata : float, optional
        Extra nodata values for inputs that do not declare theirs.
    options : RegisterOptions, optional
        All options; the keywords above, where given, override it (the defaults of
        ``resampling``, ``band``, ``order`` and ``dense`` are :class:`RegisterOptions`'s:
        bilinear, 1, 2, True; for ``tile`` see above).
    resume : bool
        Continue the unfinished job writing ``out`` (same inputs, options and version):
        tiles finished by an earlier, interrupted run are not computed again. False
        starts afresh.
    overwrite : bool
        Replace an existing ``out`` if geocoder wrote it (never anything else). An output
        equal to, inside or containing an input or the working directory is always refused.
    show_progress : Progress or bool, optional
        Progress receiver (True: a bar per phase on standard error). Default
        :func:`geocoder.get_option` ``("progress")``; None keeps the caller's display.
    via : str, PathLike or xarray.DataArray, optional
        An intermediate look: register ``via`` onto ``base`` and ``distorted`` onto ``via``,
        compose the two fields and resample the original ``distorted`` once through the
        chain (:func:`geocoder.pipeline.compose.register_via`, seed 003 sec. 10).

    Returns
    -------
    xarray.Dataset
        ``registered`` (band, y, x), ``dx``, ``dy`` (float32), ``status`` (uint8), with the
        base CRS; ``attrs["summary"]`` (JSON) and ``attrs["mapping"]``. The tie points are
        in the ``tiepoints`` group of ``out`` and in ``Dataset.attrs`` as ``tiepoints``
        when computed in memory.
    """
    if via is not None:
        if bands or (options is not None and options.bands):
            raise ValueError("matching several bands (bands) is not available through an intermediate look (via)")
        from .compose import register_via

        return register_via(base, distorted, via, out=out, resampling=resampling, tile=tile, client=client,
                            scheduler=scheduler, band=band, dist_band=dist_band, order=order, dense=dense, nodata=nodata,
                            dist_nodata=dist_nodata, options=options, resume=resume, overwrite=overwrite,
                            show_progress=show_progress)
    given = {"tile": tile, "resampling": resampling, "band": band, "dist_band": dist_band, "order": order, "dense": dense,
             "bands": None if bands is None else tuple(int(b) for b in bands)}
    opts = replace(options or RegisterOptions(), **{k: v for k, v in given.items() if v is not None})
    opts.validate()
    if out is not None:
        out = check_output(out, inputs=(base, distorted), overwrite=overwrite)
        if not storage.is_url(out) and not os.path.isdir(os.path.dirname(out)):
            raise InputError(out, "the output's parent directory does not exist")
    if opts.tile is None:  # neither the keyword nor ``options``: set_options, Dask config, or by the base's size
        shape = base if isinstance(base, xr.DataArray) else open_scene(base, nodata=nodata, grid=True)
        opts = replace(opts, tile=default_tile((shape.sizes["y"], shape.sizes["x"])))
        opts.validate()
    tile = opts.tile
    bscene = base if isinstance(base, xr.DataArray) else open_scene(base, chunks=tile, nodata=nodata, grid=True)
    dscene = distorted if isinstance(distorted, xr.DataArray) else open_scene(distorted, chunks=tile, nodata=dist_nodata)
    for scene, b in ((bscene, opts.band), (dscene, opts.dist_band or opts.band), *((s, b) for s in (bscene, dscene)
                                                                                   for b in opts.bands)):
        if not 1 <= b <= scene.sizes["band"]:
            raise InputError(scene.attrs.get("source"), f"has {scene.sizes['band']} band(s); band {b} does not exist")
    for scene in (bscene, dscene):
        _check_size(scene)
    summary = RegisterSummary(base=bscene.attrs.get("source", "base"), distorted=dscene.attrs.get("source", "distorted"))
    timer = _Timer(summary)
    key = _job_key(base, distorted, bscene, dscene, opts, nodata, dist_nodata) if out is not None else "in-memory"
    # the lock first: a second job to the same output is refused before it starts a cluster
    job = open_job(out, key, resume) if out is not None else Job(tempfile.mkdtemp(prefix=".geocoder-job-"), key)
    if job.resumed:
        log.info("resuming the job in %s", job.path)
    if show_progress is None:
        show_progress = get_option("progress")
    with JobRun(job, resumable=out is not None) as run, progress.reporting(show_progress), \
            dask_client(client, scheduler) as c:
        run.connected = c.scheduler.address
        progress.current().message(f"Dask dashboard: {c.dashboard_link}")
        ds, counts, tp, overviews = _run(job, bscene, dscene, opts, summary, timer, c, in_memory=out is None)
        summary.status_counts = {Status(i).name.lower(): int(n) for i, n in enumerate(counts) if n}
        if out is None:
            summary.job = job.report()
            ds.attrs["summary"] = json.dumps(asdict(summary))
            ds.attrs["tiepoints"] = _tiepoint_dataset(tp)
            return ds
        store = job.file("output.zarr")
        with timer("overview levels"):
            overviews.compute(client=c)  # in the store before it is committed
        summary.job = job.report()
        storage.open_group(store, mode="r+").attrs["summary"] = json.dumps(asdict(summary))
        commit_output(store, out, overwrite=overwrite)
    return xr.open_zarr(out, decode_coords="all", consolidated=False)


def _run(job: Job, bscene, dscene, opts: RegisterOptions, summary: RegisterSummary, timer, c, *, in_memory: bool):
    """The stages of :func:`register` inside a job: the dataset, its status counts, the tie
    points and, written to the job's output store, its overview levels still to compute (the tie
    points are in the store then; None in memory)."""
    band, dband = opts.band - 1, (opts.dist_band or opts.band) - 1
    factor = overview_factor(bscene, dscene)

    def figures(b: int) -> Callable[[xr.DataArray], Delayed]:
        # the content check's figures and the coarse alignment's overview of the matching band,
        # made from the chunks as they are ingested (not by two more passes over the stores)
        return lambda image: ingest_figures(image.data, b, factor)

    with timer("ingest"):
        ingested = ingest_all(job, {"base": bscene, "distorted": dscene}, opts.tile, c,
                              reduce={"base": figures(band), "distorted": figures(dband)})
        bscene, dscene = ingested["base"], ingested["distorted"]
    reduced = [s.attrs.pop("reduced", None) for s in (bscene, dscene)]
    fresh = all(r is not None for r in reduced)
    if not job.done("content"):
        _check_content([(bscene, opts.band), (dscene, opts.dist_band or opts.band)],
                       [r[:3] for r in reduced] if fresh else None)
        job.save("content")
    breader = WindowReader(job.file("base.zarr"))
    dreader = WindowReader(job.file("distorted.zarr"))
    grid = TileGrid.from_chunks(bscene.data.chunks[1:])  # the job's tiles, from here down
    tp, mapping, coarse = find_tiepoints(bscene, dscene, breader, dreader, opts, summary, timer, job,
                                         overviews=(reduced[0][3], reduced[1][3]) if fresh else None, grid=grid)
    dx, dy = polynomial_displacement(mapping, grid.chunks)
    extra = {}
    if opts.dense:
        with timer("dense matching"):
            bands = None
            if opts.bands:
                bands = job.cached("band-scales", lambda: Bands.of(bscene, dscene, opts.bands))
            result = grow_tiles(
                breader, dreader, grid, seeds_from_tiepoints(tp, mapping), mapping, job.file("dense.zarr"),
                band=opts.band - 1, dist_band=(opts.dist_band or opts.band) - 1, opts=opts.matching, job=job,
                bands=bands,
            )
            # the post-filter, stored, with the row sums of the line estimates from the same tasks
            field_ = dense_field(result, (dx, dy), opts.postfilter, store=True, job=job,
                                 line_sums_of=mapping if opts.lines.enabled else None)
        summary.dense_rounds = result.rounds
        summary.dense_converged = result.converged
        summary.dense_new_per_round = result.new_per_round
        if opts.lines.enabled:
            with timer("line estimates"):
                correlation = 2 * opts.matching.alsc.radius + 1
                rows, fits = row_corrections(field_, (dx, dy), opts.lines, correlation=correlation,
                                             line_correlation=2 * opts.matching.alsc.ry + 1,
                                             sums=field_.get("line_sums"))
                field_ = line_field(result.store, grid.chunks, mapping, rows, fits, opts.lines, correlation=correlation)
        dx, dy = field_["dx"], field_["dy"]
        extra = {k: field_[k] for k in ("sigma_x", "sigma_y", "correlation")}
    registered = resample(dreader, dx, dy, method=opts.resampling)
    status = model_status(registered)
    if opts.dense:
        status = da.where(status == Status.OUTSIDE, status, field_["status"]).astype(np.uint8)
    ds = _output_dataset(bscene, registered, dx, dy, status, mapping, coarse, opts, extra)
    with timer("resampling"):
        if in_memory:
            ds = ds.compute()
            counts = np.bincount(ds.status.values.ravel(), minlength=len(Status))
        else:
            store = job.file("output.zarr")
            if not job.done("output-created"):
                storage.create_store(ds, store)
                job.save("output-created")
            # the store's other metadata (tie points, the overview levels' groups) is written by
            # the client while the workers compute the tiles, not after them with the workers idle
            with ThreadPoolExecutor(1, thread_name_prefix="geocoder-metadata") as pool:
                metadata = pool.submit(_output_metadata, store, tp)
                counts = write_tiles(ds, store, grid, job)
                overviews = metadata.result()
            return ds, counts, tp, overviews
    return ds, counts, tp, None


def _output_metadata(store: str, tp: TiePoints) -> OverviewPlan:
    """The tie points into the output ``store`` (group ``tiepoints``), and its overview levels
    planned (their groups written, :func:`geocoder.multiscales.plan_overviews`)."""
    _tiepoint_dataset(tp).to_zarr(store, group="tiepoints", mode="w", zarr_format=3, consolidated=False)
    return plan_overviews(store)


#: Smallest image side geocoder registers (interest windows, patches and pyramids need room).
MIN_SIDE = 32


def _check_size(scene: xr.DataArray) -> None:
    h, w = scene.sizes["y"], scene.sizes["x"]
    if min(h, w) < MIN_SIDE:
        raise InputError(scene.attrs.get("source"), f"is {w} x {h} px; registration needs at least {MIN_SIDE} x {MIN_SIDE}")


def _check_content(scenes: list[tuple[xr.DataArray, int]], figures: list[tuple] | None = None) -> None:
    """Refuse a matching band with fewer than ``MIN_SIDE**2`` valid pixels or one value only.

    ``scenes`` are ``(scene, 1-based band)``; their figures (:func:`_band_statistics`) are
    ``figures`` when known, else computed in one graph.
    """
    if figures is None:
        figures = dask.compute(*(_band_statistics(scene.data[band - 1 : band]) for scene, band in scenes))
    for (scene, band), (n, lo, hi) in zip(scenes, figures):
        n, lo, hi = n[0], lo[0], hi[0]
        source = scene.attrs.get("source")
        if n == 0:
            raise InputError(source, f"band {band} has no valid pixels (all nodata)")
        if n < MIN_SIDE**2:
            raise InputError(source, f"band {band} has only {int(n)} valid pixels; registration needs at least {MIN_SIDE**2}")
        if lo == hi:
            raise InputError(source, f"band {band} is constant ({float(lo):g} everywhere): there is nothing to match")


def ingest_figures(image: da.Array, band: int, factor: int) -> Delayed:
    """Lazy figures of band ``band`` (0-based) of a ``(band, y, x)`` scene, one task per chunk
    (:mod:`geocoder.kernels.figures`): ``(count, minimum, maximum)`` of its finite pixels as
    :func:`_band_statistics` gives them, and its block mean over ``factor`` squares as
    :func:`geocoder.pipeline.coarse.overview` gives it.

    The chunks are taken from ``image``'s own graph (not optimised apart), so computed with the
    store's writes they are read once for both.
    """
    cells = (image.shape[1] // factor, image.shape[2] // factor)
    rows, cols = np.r_[0, np.cumsum(image.chunks[1])], np.r_[0, np.cumsum(image.chunks[2])]
    blocks = image.to_delayed(optimize_graph=False)
    parts = [dask.delayed(chunk_figures, pure=True)(blocks[0, i, j], band, int(rows[i]), int(cols[j]), factor, cells)
             for i in range(len(rows) - 1) for j in range(len(cols) - 1)]
    return dask.delayed(combine_figures, pure=True)(parts, cells)


def _band_statistics(image: da.Array) -> tuple[da.Array, da.Array, da.Array]:
    """Per band of a ``(band, y, x)`` array: the number of valid (finite) pixels, their minimum and maximum (lazy)."""
    valid = da.isfinite(image)
    return (valid.sum(axis=(1, 2)), da.where(valid, image, np.inf).min(axis=(1, 2)),
            da.where(valid, image, -np.inf).max(axis=(1, 2)))


def job_directory(out: str) -> str:
    """Where the job writing ``out`` keeps its finished work until ``out`` is committed.

    Beside ``out`` on the same filesystem (local directory or object-store prefix).
    """
    out = storage.normalize(out)
    return storage.sibling(out, f".{storage.split(out)[1]}.geocoder-job")


def open_job(out: str, key: str, resume: bool) -> Job:
    """The job writing ``out`` (its directory beside it, :func:`job_directory`), resumed if
    ``resume`` and an interrupted run of the same ``key`` left one, else started afresh.

    Raises
    ------
    InputError
        If the job's files cannot be written beside ``out`` (naming ``out``).
    """
    try:
        job = Job(job_directory(out), key, target=out)
        if not resume and job.resumed:
            job.remove()
            job = Job(job_directory(out), key, target=out)
    except OSError as exc:  # no such bucket, no permission, unreachable endpoint ...
        raise InputError(out, f"cannot write the job's files beside the output ({type(exc).__name__}: {exc})") from exc
    return job


def _job_key(base, distorted, bscene, dscene, opts: RegisterOptions, nodata, dist_nodata) -> str:
    from .._version import __version__

    return fingerprint(
        base=input_identity(bscene if isinstance(base, xr.DataArray) else base),
        distorted=input_identity(dscene if isinstance(distorted, xr.DataArray) else distorted),
        options=repr(opts), nodata=[nodata, dist_nodata], version=__version__,
    )


def ingest_all(job: Job, scenes: dict[str, xr.DataArray], tile: int, client,
               reduce: dict[str, Callable[[xr.DataArray], Any]] | None = None) -> dict[str, xr.DataArray]:
    """Ingest the job's scenes (name -> scene) to ``NAME.zarr`` in its directory, all in one graph.

    A scene whose stage finished in an earlier run is re-opened, not written again.
    ``reduce`` (name -> function of the image as written, see
    :func:`geocoder.scene.ingest_scenes`) is computed in the same graph for the scenes written
    now; its value is their ``attrs["reduced"]``.
    Returns the scenes re-opened from their stores, by name.
    """
    reduce = reduce or {}
    out: dict[str, xr.DataArray] = {}
    todo = []
    for name, scene in scenes.items():
        path = job.file(f"{name}.zarr")
        ntiles = len(TileGrid.regular(scene.sizes["y"], scene.sizes["x"], tile))
        if job.done(f"ingest-{name}") and storage.is_store(path):
            job.count(f"ingest-{name}", run=0, skipped=ntiles)
            out[name] = open_scene(path, chunks=tile)
            out[name].attrs["source"] = scene.attrs.get("source", name)
        else:
            job.note_unfinished(ntiles)
            todo.append((name, scene, path, ntiles))
    if todo:
        bar = progress.current()
        bar.phase(f"ingest ({', '.join(name for name, *_ in todo)})", len(todo))
        # complete once each stage is saved
        written = ingest_scenes([scene for _, scene, *_ in todo], [path for *_, path, _ in todo], tile=tile, client=client,
                                reduce=[reduce.get(name) for name, *_ in todo])
        bar.advance(len(todo))
        bar.close()
        for (name, scene, _, ntiles), reopened in zip(todo, written):
            job.count(f"ingest-{name}", run=ntiles, skipped=0)
            job.save(f"ingest-{name}")
            reopened.attrs["source"] = scene.attrs.get("source", name)
            out[name] = reopened
    return {name: out[name] for name in scenes}


def _write_tile(store: str, window: tuple[int, int, int, int], names: tuple[str, ...], *blocks: np.ndarray) -> np.ndarray:
    r0, r1, c0, c1 = window
    g = storage.Arrays(store, mode="r+")
    for name, block in zip(names, blocks):
        g[name][..., r0:r1, c0:c1] = block
    status = blocks[names.index("status")]
    return np.bincount(np.asarray(status).ravel(), minlength=len(Status))


def write_tiles(ds: xr.Dataset, store: str, grid: TileGrid, job: Job) -> np.ndarray:
    """Compute every output tile and write all its variables into their Zarr regions.

    Each tile is one task (sharing the graph upstream); a finished tile is recorded by the
    job, so a rerun writes only the missing ones. Returns the status counts.
    """
    names = tuple(ds.data_vars)
    blocks = {n: ds[n].data.to_delayed(optimize_graph=False) for n in names}
    tasks = {}
    for t in grid:
        parts = [blocks[n][(0, t.iy, t.ix) if ds[n].ndim == 3 else (t.iy, t.ix)] for n in names]
        tasks[t.key] = dask.delayed(_write_tile, pure=True)(store, (t.row0, t.row1, t.col0, t.col1), names, *parts)
    done = job.run_tiles("output", tasks, phase="resampling and writing")
    return np.sum(list(done.values()), axis=0)


def _output_dataset(scene, registered, dx, dy, status, mapping: PolyMap, coarse: CoarseAlignment, opts: RegisterOptions, extra: dict) -> xr.Dataset:
    coords = {k: v for k, v in scene.coords.items() if k != "band"}
    coords["band"] = np.arange(1, registered.shape[0] + 1)  # the distorted image's bands
    ds = xr.Dataset(
        {
            "registered": (("band", "y", "x"), registered),
            "dx": (("y", "x"), dx, {"long_name": "x_distorted - x_base", "units": "pixel"}),
            "dy": (("y", "x"), dy, {"long_name": "y_distorted - y_base", "units": "pixel"}),
            "status": (("y", "x"), status, status_attrs()),
            **{
                k: (("y", "x"), v, {"long_name": LONG_NAMES[k], "units": "pixel" if k != "correlation" else "1"})
                for k, v in extra.items()
            },
        },
        coords=coords,
    )
    ds["registered"].attrs["long_name"] = "distorted image resampled onto the base grid"
    ds["band"].attrs["long_name"] = "band of the distorted image (1-based)"
    if scene.attrs.get("georeferenced"):
        ds = georeference(ds, scene.rio.crs, scene.rio.transform())
    else:
        ds = pixel_grid(ds)
    ds.attrs.update(
        {
            "mapping": json.dumps(mapping.to_dict()),
            "coarse_alignment": json.dumps({"method": coarse.method, "matrix": np.asarray(coarse.matrix).tolist(), "factor": coarse.factor, "peak": coarse.peak}),
            "resampling": opts.resampling,
            "polynomial_terms": json.dumps(exponents(opts.order)),
            "source_base": scene.attrs.get("source", ""),
            **product_attrs("register"),
        }
    )
    return ds
