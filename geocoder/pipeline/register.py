"""``register(base, distorted)``: the end-to-end polynomial registration job.

Ingest both scenes to Zarr, align coarsely, find interest points and tie points tile by
tile, fit a robust global polynomial on one node, then resample the original distorted
image once onto the base grid, writing everything to one Zarr store atomically.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field, replace

import dask.array as da
import numpy as np
import xarray as xr

from ..errors import InputError, MatchingError
from ..kernels.polynomial import PolyMap, exponents
from ..match.coarse import CoarseAlignment
from ..match.correspondence import CorrespondenceOptions
from ..match.tiepoints import TiePoints
from ..quality.postfilter import PostFilterOptions
from ..runtime import dask_client
from ..scene import WindowReader, commit_store, ingest, open_scene, temporary_path
from ..status import Status, legend
from ..tiles import TileGrid
from .coarse import coarse_alignment
from .correspond import fit_global, match_tiles
from .dense import DenseOptions, dense_field, grow_tiles, seeds_from_tiepoints
from .detect import InterestOptions, interest_points
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
    """Everything :func:`register` can be told, with the seed's defaults."""

    tile: int = 512
    resampling: str = "bilinear"
    band: int = 1
    dist_band: int | None = None
    order: int = 2
    passes: int = 2
    min_tiepoints: int = 12
    interest: InterestOptions = field(default_factory=InterestOptions)
    correspondence: CorrespondenceOptions = field(default_factory=CorrespondenceOptions)
    use_georeference: bool = True
    dense: bool = True
    matching: DenseOptions = field(default_factory=DenseOptions)
    postfilter: PostFilterOptions = field(default_factory=PostFilterOptions)

    def validate(self) -> None:
        if self.resampling not in RESAMPLING:
            raise ValueError(f"resampling must be one of {RESAMPLING}, got {self.resampling!r}")
        if self.tile < 64 or self.tile % self.interest.cell:
            raise ValueError(f"tile must be a multiple of {self.interest.cell} and >= 64, got {self.tile}")
        if not 1 <= self.order <= 3:
            raise ValueError(f"order must be 1, 2 or 3, got {self.order}")


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
) -> tuple[TiePoints, PolyMap, CoarseAlignment]:
    """Coarse alignment, interest points and correspondence passes; gathered tie points."""
    band = opts.band - 1
    dband = (opts.dist_band or opts.band) - 1
    with timer("coarse alignment"):
        coarse = coarse_alignment(base, dist, band=band, dist_band=dband, use_georeference=opts.use_georeference)
    summary.coarse_method = f"{coarse.method} (pyramid 1/{coarse.factor}, peak {coarse.peak:.2f})"
    base_shape = (base.sizes["y"], base.sizes["x"])
    dist_shape = (dist.sizes["y"], dist.sizes["x"])
    _check_overlap(coarse.mapping, base_shape, dist_shape, base.attrs["source"], dist.attrs["source"])
    with timer("interest points"):
        bpts = interest_points(base.data[band], opts.interest)
        dpts = interest_points(dist.data[dband], opts.interest)
    summary.base_points, summary.distorted_points = len(bpts), len(dpts)
    for pts, scene in ((bpts, base), (dpts, dist)):
        if len(pts) < opts.min_tiepoints:
            raise InputError(scene.attrs["source"], f"has too little texture: {len(pts)} interest points found")
    grid = TileGrid.from_chunks(base.data.chunks[1:])
    predict = coarse.mapping
    copts = opts.correspondence
    tp, mapping = TiePoints.empty(), predict
    with timer("correspondence"):
        # pass 1: pairs of interest points (seed 000 sec. 4.4); if the images defeat it but
        # the coarse alignment is a full affine, match from the coarse prediction instead
        found, _ = match_tiles(base_reader, dist_reader, grid, bpts, dpts, predict, band=band, dist_band=dband, opts=copts)
        summary.pass_tiepoints.append(len(found))
        if len(found) < opts.min_tiepoints and coarse.method.endswith("+affine"):
            found, _ = match_tiles(base_reader, dist_reader, grid, bpts, dpts, predict, band=band, dist_band=dband, opts=copts, guided=True)
            summary.pass_tiepoints.append(len(found))
        if len(found) < opts.min_tiepoints:
            raise MatchingError(
                f"only {len(found)} tie points found between {base.attrs['source']} and {dist.attrs['source']}"
            )
        tp, mapping = fit_global(found, order=opts.order)
        # later passes: every base point matched from the fitted polynomial
        for _ in range(1, opts.passes):
            found, _ = match_tiles(base_reader, dist_reader, grid, bpts, dpts, mapping, band=band, dist_band=dband, opts=copts, guided=True)
            summary.pass_tiepoints.append(len(found))
            if len(found) < opts.min_tiepoints:
                break
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
    resampling: str = "bilinear",
    tile: int = 512,
    client=None,
    scheduler: str | None = None,
    band: int = 1,
    dist_band: int | None = None,
    order: int = 2,
    dense: bool = True,
    nodata: float | None = None,
    dist_nodata: float | None = None,
    options: RegisterOptions | None = None,
) -> xr.Dataset:
    """Register ``distorted`` onto the grid of ``base``.

    Parameters
    ----------
    base, distorted : str, PathLike or xarray.DataArray
        GeoTIFF/COG/Zarr paths (or scenes from :func:`geocoder.open_scene`).
    out : str or PathLike, optional
        Zarr store to write (atomically). Without it the result is computed into memory.
    resampling : {"nearest", "bilinear", "cubic", "lanczos"}
        Interpolator of the single resampling.
    tile : int
        Tile size (chunk) of all tile-parallel stages; a multiple of 64.
    client : distributed.Client, optional
        Where to run; default ``scheduler`` or ``DASK_SCHEDULER_ADDRESS``, else a local cluster.
    band, dist_band : int
        1-based band used for matching (``dist_band`` defaults to ``band``).
    order : int
        Order of the global polynomial (2 = the seed's quadratic).
    dense : bool
        Match every pixel (region-growing least squares with halo exchange, scan-line
        post-filter); False stops at the global polynomial.
    nodata, dist_nodata : float, optional
        Extra nodata values for inputs that do not declare theirs.
    options : RegisterOptions, optional
        All other options; the keywords above override it.

    Returns
    -------
    xarray.Dataset
        ``registered`` (band, y, x), ``dx``, ``dy`` (float32), ``status`` (uint8), with the
        base CRS; ``attrs["summary"]`` (JSON) and ``attrs["mapping"]``. The tie points are
        in the ``tiepoints`` group of ``out`` and in ``Dataset.attrs`` as ``tiepoints``
        when computed in memory.
    """
    opts = replace(
        options or RegisterOptions(), tile=tile, resampling=resampling, band=band,
        dist_band=dist_band, order=order, dense=dense,
    )
    opts.validate()
    if out is not None:
        out = os.fspath(out)
        parent = os.path.dirname(os.path.abspath(out))
        if not os.path.isdir(parent):
            raise InputError(out, "the output's parent directory does not exist")
    bscene = base if isinstance(base, xr.DataArray) else open_scene(base, chunks=tile, nodata=nodata)
    dscene = distorted if isinstance(distorted, xr.DataArray) else open_scene(distorted, chunks=tile, nodata=dist_nodata)
    for scene, b in ((bscene, opts.band), (dscene, opts.dist_band or opts.band)):
        if not 1 <= b <= scene.sizes["band"]:
            raise InputError(scene.attrs.get("source"), f"has {scene.sizes['band']} band(s); band {b} does not exist")
    summary = RegisterSummary(base=bscene.attrs.get("source", "base"), distorted=dscene.attrs.get("source", "distorted"))
    timer = _Timer(summary)
    work = tempfile.mkdtemp(prefix=".geocoder-work-", dir=os.path.dirname(os.path.abspath(out)) if out else None)
    tmp_out = temporary_path(out) if out else None
    try:
        with dask_client(client, scheduler) as c:
            with timer("ingest"):
                bscene = ingest(bscene, os.path.join(work, "base.zarr"), tile=opts.tile, client=c)
                dscene = ingest(dscene, os.path.join(work, "distorted.zarr"), tile=opts.tile, client=c)
            breader = WindowReader(os.path.join(work, "base.zarr"))
            dreader = WindowReader(os.path.join(work, "distorted.zarr"))
            tp, mapping, coarse = find_tiepoints(bscene, dscene, breader, dreader, opts, summary, timer)
            chunks = bscene.data.chunks[1:]
            dx, dy = polynomial_displacement(mapping, chunks)
            extra = {}
            if opts.dense:
                with timer("dense matching"):
                    grid = TileGrid.from_chunks(chunks)
                    state = os.path.join(work, "dense.zarr")
                    result = grow_tiles(
                        breader, dreader, grid, seeds_from_tiepoints(tp, mapping), mapping, state,
                        band=opts.band - 1, dist_band=(opts.dist_band or opts.band) - 1, opts=opts.matching,
                    )
                summary.dense_rounds = result.rounds
                summary.dense_converged = result.converged
                summary.dense_new_per_round = result.new_per_round
                field_ = dense_field(state, opts.tile, (dx, dy), opts.postfilter)
                dx, dy = field_["dx"], field_["dy"]
                extra = {k: field_[k] for k in ("sigma_x", "sigma_y", "correlation")}
            registered = resample(dreader, dx, dy, method=opts.resampling)
            status = model_status(registered)
            if opts.dense:
                status = da.where(status == Status.OUTSIDE, status, field_["status"]).astype(np.uint8)
            ds = _output_dataset(bscene, registered, dx, dy, status, mapping, coarse, opts, extra)
            with timer("resampling"):
                if out is None:
                    ds = ds.compute()
                else:
                    ds.to_zarr(tmp_out, mode="w", zarr_format=3, consolidated=False, compute=False).compute()
            written = ds.status if out is None else xr.open_zarr(tmp_out, consolidated=False).status
            counts = np.bincount(np.asarray(written.values).ravel(), minlength=len(Status))
            summary.status_counts = {Status(i).name.lower(): int(n) for i, n in enumerate(counts) if n}
            ds.attrs["summary"] = json.dumps(asdict(summary))
            if out is None:
                ds.attrs["tiepoints"] = _tiepoint_dataset(tp)
                return ds
            _tiepoint_dataset(tp).to_zarr(tmp_out, group="tiepoints", mode="w", zarr_format=3, consolidated=False)
            import zarr

            zarr.open_group(tmp_out, mode="r+").attrs["summary"] = json.dumps(asdict(summary))
            commit_store(tmp_out, out)
    except BaseException:
        if tmp_out:
            shutil.rmtree(tmp_out, ignore_errors=True)
        raise
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result = xr.open_zarr(out, decode_coords="all", consolidated=False)
    return result


def _output_dataset(scene, registered, dx, dy, status, mapping: PolyMap, coarse: CoarseAlignment, opts: RegisterOptions, extra: dict) -> xr.Dataset:
    coords = {k: v for k, v in scene.coords.items() if k != "band"}
    coords["band"] = np.arange(1, registered.shape[0] + 1)  # the distorted image's bands
    ds = xr.Dataset(
        {
            "registered": (("band", "y", "x"), registered),
            "dx": (("y", "x"), dx, {"long_name": "x_distorted - x_base", "units": "pixel"}),
            "dy": (("y", "x"), dy, {"long_name": "y_distorted - y_base", "units": "pixel"}),
            "status": (("y", "x"), status, {"flag_meanings": json.dumps(legend())}),
            **{
                k: (("y", "x"), v, {"long_name": LONG_NAMES[k], "units": "pixel" if k != "correlation" else "1"})
                for k, v in extra.items()
            },
        },
        coords=coords,
    )
    if scene.attrs.get("georeferenced"):
        ds = ds.rio.write_crs(scene.rio.crs).rio.write_transform(scene.rio.transform())
    ds.attrs.update(
        {
            "mapping": json.dumps(mapping.to_dict()),
            "coarse_alignment": json.dumps({"method": coarse.method, "matrix": np.asarray(coarse.matrix).tolist(), "factor": coarse.factor, "peak": coarse.peak}),
            "resampling": opts.resampling,
            "polynomial_terms": json.dumps(exponents(opts.order)),
            "source_base": scene.attrs.get("source", ""),
        }
    )
    return ds
