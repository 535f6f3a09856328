"""Registration chains (seed 003 sec. 10): ``compose(ab, bc)`` and ``register(..., via=MIDDLE)``.

``compose`` turns the field of a registration of B onto A (``d_AB``, on A's grid) and of C
onto B (``d_BC``, on B's grid) into C onto A (``d_AC``, on A's grid), one task per output
tile: each task takes its tile of ``d_AB``, works out the window of ``d_BC`` its positions
fall in and reads exactly that window from the second store
(:func:`geocoder.kernels.compose.compose_fields` does the arithmetic).

``register_via`` registers an extreme look through an intermediate one: MIDDLE onto BASE,
DISTORTED onto MIDDLE, composes the two fields and resamples the ORIGINAL distorted image
once through the composed field.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
import time
from dataclasses import asdict, replace

import dask.array as da
import numpy as np
import xarray as xr
import zarr

from .. import storage
from ..conventions import georeference, pixel_grid, status_attrs
from ..errors import InputError
from ..kernels.compose import FieldBlock, compose_fields, field_window
from ..multiscales import write_overviews
from ..options import get_option
from ..outputs import check_output, commit_output, product_attrs
from ..runtime import dask_client
from ..scene import WindowReader, ingest, open_scene
from ..status import Status
from .job import Job, JobRun, fingerprint

log = logging.getLogger("geocoder")

#: Variables of a displacement store that the composition reads (``dx``, ``dy`` required).
FIELD_VARS = ("dx", "dy", "sigma_x", "sigma_y", "status", "correlation")
#: Layers of the composed block, in the order :func:`_compose_block` stacks them.
_LAYERS = ("dx", "dy", "sigma_x", "sigma_y", "correlation", "status")


class FieldReader:
    """Pickleable, lazy reader of windows of a displacement store (the second field of a chain).

    Parameters
    ----------
    store : str
        Zarr store (path or fsspec URL) holding ``dx``, ``dy`` and optionally ``sigma_x``,
        ``sigma_y``, ``status``, ``correlation`` on its grid (a :func:`geocoder.register`
        output).
    """

    def __init__(self, store: str) -> None:
        self.store = os.fspath(store)
        self._group = None

    def __getstate__(self):
        return {"store": self.store}

    def __setstate__(self, state):
        self.store, self._group = state["store"], None

    @property
    def group(self) -> zarr.Group:
        if self._group is None:
            self._group = zarr.open_group(self.store, mode="r")
        return self._group

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of the field's grid."""
        return tuple(self.group["dx"].shape)

    def read(self, window: tuple[int, int, int, int]) -> FieldBlock:
        """The field's variables in ``window`` = ``(row0, row1, col0, col1)`` (inside the grid)."""
        r0, r1, c0, c1 = window
        names = set(self.group.array_keys())
        parts = {k: (self.group[k][r0:r1, c0:c1] if k in names else None) for k in FIELD_VARS}
        return FieldBlock(**parts, row0=r0, col0=c0)


def _compose_block(*blocks, block_info=None, names: tuple[str, ...], reader: FieldReader) -> np.ndarray:
    (r0, r1), (c0, c1) = block_info[0]["array-location"]
    parts = dict(zip(names, blocks))
    first = FieldBlock(**{k: parts.get(k) for k in FIELD_VARS}, row0=r0, col0=c0)
    out = np.full((len(_LAYERS), r1 - r0, c1 - c0), np.nan, dtype=np.float64)
    out[-1] = int(Status.OUTSIDE)
    window = field_window(first, reader.shape)
    if window is None:
        return out
    c = compose_fields(first, reader.read(window))
    out[0], out[1], out[2], out[3] = c.dx, c.dy, c.sigma_x, c.sigma_y
    if c.correlation is not None:
        out[4] = c.correlation
    out[5] = c.status
    return out


def _open_field(field, what: str) -> xr.Dataset:
    if isinstance(field, xr.Dataset):
        ds = field
    else:
        location = os.fspath(field)
        try:
            ds = xr.open_zarr(location, consolidated=False, decode_coords="all")
        except (FileNotFoundError, ValueError, KeyError, OSError) as exc:
            raise InputError(location, f"cannot be opened as the {what} displacement store ({type(exc).__name__}: {exc})") from exc
    source = ds.encoding.get("source", "the dataset") if isinstance(field, xr.Dataset) else os.fspath(field)
    for k in ("dx", "dy"):
        if k not in ds or ds[k].dims != ("y", "x"):
            raise InputError(source, f"is not a displacement store: no '{k}' (y, x) variable")
    return ds


def compose_lazy(ab: xr.Dataset, second: str, *, tile: int | None = None) -> xr.Dataset:
    """The composed field of ``ab`` (A -> B, on A's grid) and the store ``second`` (B -> C), lazy.

    Parameters
    ----------
    ab : xarray.Dataset
        The first field (``dx``, ``dy`` and optionally ``sigma_x``, ``sigma_y``, ``status``,
        ``correlation``), numpy or dask backed.
    second : str
        Zarr store of the second field, read window by window by the tasks.
    tile : int, optional
        Output tile; default the first field's chunks (512 for numpy-backed fields).

    Returns
    -------
    xarray.Dataset
        ``dx``, ``dy``, ``sigma_x``, ``sigma_y`` (float32), ``status`` (uint8) and, when both
        fields carry one, ``correlation`` on A's grid, one task per tile.
    """
    reader = FieldReader(second)
    names = tuple(k for k in FIELD_VARS if k in ab)
    arrays = []
    for k in names:
        a = ab[k].data
        if not isinstance(a, da.Array):
            a = da.from_array(np.asarray(a), chunks=tile or 512)
        elif tile is not None:
            a = a.rechunk(tile)
        arrays.append(a)
    chunks = arrays[0].chunks
    arrays = [a.rechunk(chunks) for a in arrays]
    stack = da.map_blocks(_compose_block, *arrays, new_axis=0, chunks=((len(_LAYERS),), *chunks), dtype=np.float64,
                          names=names, reader=reader, meta=np.empty((0, 0, 0), dtype=np.float64))
    has_corr = "correlation" in ab and "correlation" in reader.group.array_keys()
    units = {"long_name": "", "units": "pixel"}
    data = {
        "dx": (stack[0].astype(np.float32), {**units, "long_name": "x_distorted - x_base (composed chain)"}),
        "dy": (stack[1].astype(np.float32), {**units, "long_name": "y_distorted - y_base (composed chain)"}),
        "sigma_x": (stack[2].astype(np.float32), {**units, "long_name": "standard deviation of dx, propagated through the chain"}),
        "sigma_y": (stack[3].astype(np.float32), {**units, "long_name": "standard deviation of dy, propagated through the chain"}),
    }
    if has_corr:
        data["correlation"] = (stack[4].astype(np.float32), {"long_name": "smaller correlation coefficient of the two matches",
                                                             "units": "1"})
    data["status"] = (stack[5].astype(np.uint8), status_attrs())
    coords = {k: v for k, v in ab.coords.items() if k in ("x", "y")}
    ds = xr.Dataset({k: (("y", "x"), v, attrs) for k, (v, attrs) in data.items()}, coords=coords)
    return on_grid_of(ds, ab)


def on_grid_of(ds: xr.Dataset, like: xr.Dataset) -> xr.Dataset:
    """``ds`` with the georeference of ``like`` (the base grid), or its pixel grid when it has none."""
    crs = like.rio.crs if "spatial_ref" in like.coords else None
    if crs is not None:
        return georeference(ds, crs, like.rio.transform())
    return pixel_grid(ds)


def compose(
    ab,
    bc,
    *,
    out: str | os.PathLike | None = None,
    tile: int | None = None,
    client=None,
    scheduler: str | None = None,
    overwrite: bool = False,
) -> xr.Dataset:
    """Compose two displacement fields of a registration chain: A -> B and B -> C into A -> C.

    Direction, as :func:`geocoder.register` writes a field (``d = p_distorted - p_base`` on
    the base grid): ``ab`` is the output of ``register(A, B)`` (base A, distorted B), so
    ``p + d_AB(p)`` is the position in B of A's pixel ``p``; ``bc`` is the output of
    ``register(B, C)``. The result is the field ``register(A, C)`` would give, on A's grid::

        d_AC(p) = d_AB(p) + d_BC(p + d_AB(p))

    with ``d_BC`` interpolated bilinearly, the covariance propagated to first order
    (``C_AC = J C_AB J^T + C_BC``, ``J`` the Jacobian of B -> C), the status the worse of the
    two (:data:`geocoder.kernels.compose.STATUS_ORDER`) and ``OUTSIDE`` (NaN displacement)
    where ``p + d_AB(p)`` leaves B's grid or meets a pixel of B without a displacement.

    Parameters
    ----------
    ab, bc : str, PathLike or xarray.Dataset
        The two fields: Zarr stores (paths or fsspec URLs) or datasets with ``dx``, ``dy``
        (and optionally ``sigma_x``, ``sigma_y``, ``status``, ``correlation``) on dims
        ``(y, x)``. A ``bc`` dataset is first written to a temporary local store, since the
        tasks read it window by window.
    out : str or PathLike, optional
        Zarr store to write, committed atomically; without it the result is computed into
        memory.
    tile : int, optional
        Output tile (one task each); default the chunks of ``ab``'s store, else
        :func:`geocoder.get_option` ``("tile")``.
    client : distributed.Client, optional
        Where to run (default ``scheduler``, ``DASK_SCHEDULER_ADDRESS``, else a local cluster).
    scheduler : str, optional
        Address of a Dask scheduler when no ``client`` is given.
    overwrite : bool
        Replace an existing ``out`` if geocoder wrote it (never anything else).

    Returns
    -------
    xarray.Dataset
        ``dx``, ``dy``, ``sigma_x``, ``sigma_y`` (float32), ``status`` (uint8), and
        ``correlation`` when both fields carry it, on A's grid with A's georeference;
        ``attrs["chain"]`` (JSON) names the two fields.

    Raises
    ------
    InputError
        If a field cannot be opened or holds no ``dx``/``dy``.
    """
    inputs = tuple(f for f in (ab, bc) if not isinstance(f, xr.Dataset))
    if out is not None:
        out = check_output(out, inputs=inputs, overwrite=overwrite)
        if not storage.is_url(out) and not os.path.isdir(os.path.dirname(out)):
            raise InputError(out, "the output's parent directory does not exist")
    first = _open_field(ab, "first")
    second = _open_field(bc, "second")
    if tile is None and not isinstance(first["dx"].data, da.Array):
        tile = get_option("tile")
    work = None
    try:
        if isinstance(bc, xr.Dataset):
            work = tempfile.mkdtemp(prefix=".geocoder-compose-")
            second_store = os.path.join(work, "second.zarr")
            second[[k for k in FIELD_VARS if k in second]].to_zarr(second_store, mode="w", zarr_format=3, consolidated=False)
        else:
            second_store = os.fspath(bc)
        with dask_client(client, scheduler) as c:
            ds = compose_lazy(first, second_store, tile=tile)
            ds.attrs.update({
                "chain": json.dumps({"first": _name(ab), "second": _name(bc)}),
                **product_attrs("compose"),
            })
            if out is None:
                return ds.compute()
            write_store(ds, out, client=c, overwrite=overwrite)
    finally:
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)
    return xr.open_zarr(out, decode_coords="all", consolidated=False)


def _name(field) -> str:
    return "dataset" if isinstance(field, xr.Dataset) else os.fspath(field)


def write_store(ds: xr.Dataset, out: str, *, client, overwrite: bool, attrs: dict | None = None) -> np.ndarray:
    """Write ``ds`` (one task per tile) to a hidden sibling of ``out``, add overviews, commit it.

    Returns the status counts (indexed by :class:`geocoder.Status`).
    """
    tmp = storage.temporary_sibling(out)
    try:
        ds.to_zarr(tmp, mode="w", zarr_format=3, consolidated=False, encoding=storage.encoding(ds))
        written = xr.open_zarr(tmp, consolidated=False)
        counts = da.bincount(written.status.data.ravel(), minlength=len(Status)).compute()
        write_overviews(tmp, client=client)
        if attrs:
            group = zarr.open_group(tmp, mode="r+")
            for k, v in attrs.items():
                group.attrs[k] = v(counts) if callable(v) else v
        commit_output(tmp, out, overwrite=overwrite)
    except BaseException:
        storage.remove(tmp)
        raise
    return counts


def register_via(
    base,
    distorted,
    via,
    *,
    out: str | os.PathLike | None = None,
    client=None,
    scheduler: str | None = None,
    resume: bool = True,
    overwrite: bool = False,
    **kwargs,
) -> xr.Dataset:
    """Register ``distorted`` onto ``base`` through the intermediate look ``via`` (seed 003 sec. 10).

    Registers ``via`` onto ``base`` and ``distorted`` onto ``via`` (each a full
    :func:`geocoder.register`), composes the two fields (:func:`compose`) and resamples
    the ORIGINAL ``distorted`` image once through the composed field. Called by
    :func:`geocoder.register` when it is given ``via``.

    Parameters
    ----------
    base, distorted, via : str, PathLike or xarray.DataArray
        The scenes; ``via`` is matched on ``band`` in both registrations.
    out : str or PathLike, optional
        Zarr store to write (atomically); the two legs' stores live in the job directory
        beside it until it is committed, so an interrupted chain resumes after its last
        finished leg. Without it the result is computed into memory.
    client, scheduler, resume, overwrite
        As :func:`geocoder.register`.
    **kwargs
        The other keywords of :func:`geocoder.register` (``tile``, ``resampling``,
        ``band``, ``dist_band``, ``options``, ...), used for both legs.

    Returns
    -------
    xarray.Dataset
        As :func:`geocoder.register`: ``registered``, ``dx``, ``dy``, ``sigma_x``,
        ``sigma_y``, ``correlation``, ``status`` on the base grid; ``attrs["summary"]``
        (the composed status counts and times) and ``attrs["chain"]`` (both legs' summaries).
    """
    from .register import (
        RegisterOptions,
        RegisterSummary,
        _job_key,
        job_directory,
        register,
    )

    opts = replace(kwargs.pop("options", None) or RegisterOptions(),
                   **{k: kwargs.pop(k) for k in ("tile", "resampling", "band", "dist_band", "order", "dense")
                      if kwargs.get(k) is not None})
    for k in ("tile", "resampling", "band", "dist_band", "order", "dense"):
        kwargs.pop(k, None)
    if opts.tile is None:
        opts = replace(opts, tile=get_option("tile"))
    opts.validate()
    dist_nodata = kwargs.pop("dist_nodata", None)
    nodata = kwargs.pop("nodata", None)
    show_progress = kwargs.pop("show_progress", None)
    if kwargs:
        raise TypeError(f"register_via() got unexpected keyword(s) {sorted(kwargs)}")
    if out is not None:
        out = check_output(out, inputs=(base, distorted, via), overwrite=overwrite)
        if not storage.is_url(out) and not os.path.isdir(os.path.dirname(out)):
            raise InputError(out, "the output's parent directory does not exist")
        key = fingerprint(chain=_job_key(base, distorted, base, distorted, opts, nodata, dist_nodata),
                          via=_job_key(via, via, via, via, opts, None, None))
        job = Job(job_directory(out), key, target=out)
        if not resume and job.resumed:
            job.remove()
            job = Job(job_directory(out), key, target=out)
    else:
        job = Job(tempfile.mkdtemp(prefix=".geocoder-job-"), "in-memory")
    legs = {"first": (base, via, replace(opts, dist_band=opts.band), nodata, None),
            "second": (via, distorted, opts, None, dist_nodata)}
    seconds: dict[str, float] = {}
    with JobRun(job, resumable=out is not None) as run, dask_client(client, scheduler) as c:
        run.connected = c.scheduler.address
        summaries = {}
        for name, (b, d, o, bn, dn) in legs.items():
            store = job.file(f"{name}.zarr")
            t0 = time.perf_counter()
            if not (job.done(name) and storage.is_store(store)):
                register(b, d, out=store, options=o, nodata=bn, dist_nodata=dn, client=c, overwrite=True,
                         resume=resume, show_progress=show_progress)
                job.save(name)
            seconds[f"register ({name} leg)"] = time.perf_counter() - t0
            summaries[name] = json.loads(zarr.open_group(store, mode="r").attrs["summary"])
        t0 = time.perf_counter()
        dscene = distorted if isinstance(distorted, xr.DataArray) else open_scene(distorted, chunks=opts.tile, nodata=dist_nodata)
        dstore = job.file("distorted.zarr")
        if not (job.done("ingest-distorted") and storage.is_store(dstore)):
            ingest(dscene, dstore, tile=opts.tile, client=c, atomic=False)
            job.save("ingest-distorted")
        seconds["ingest"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        first = xr.open_zarr(job.file("first.zarr"), decode_coords="all", consolidated=False)
        field = compose_lazy(first, job.file("second.zarr"), tile=opts.tile)
        registered = _resample(WindowReader(dstore), field, opts.resampling)
        status = da.where(da.isnan(registered).all(axis=0), np.uint8(Status.OUTSIDE), field.status.data).astype(np.uint8)
        ds = field.assign(status=(("y", "x"), status, field.status.attrs))
        ds["registered"] = (("band", "y", "x"), registered, {"long_name": "distorted image resampled onto the base grid "
                                                                          "through the composed chain"})
        ds = ds.assign_coords(band=np.arange(1, registered.shape[0] + 1))
        ds["band"].attrs["long_name"] = "band of the distorted image (1-based)"
        ds = on_grid_of(ds[["registered", *[k for k in ds.data_vars if k != "registered"]]], first)
        summary = RegisterSummary(base=_source(base, summaries["first"], "base"),
                                  distorted=_source(distorted, summaries["second"], "distorted"),
                                  coarse_method="chain via " + _source(via, summaries["second"], "base"))

        def finish(counts) -> str:
            seconds["compose and resample"] = time.perf_counter() - t0
            summary.status_counts = {Status(i).name.lower(): int(n) for i, n in enumerate(counts) if n}
            summary.seconds = dict(seconds)
            summary.job = job.report()
            return json.dumps(asdict(summary))

        chain = json.dumps({"via": _source(via, summaries["second"], "base"), "first": summaries["first"],
                            "second": summaries["second"]})
        ds.attrs.update({"resampling": opts.resampling, "source_base": summary.base, **product_attrs("register")})
        if out is None:
            ds = ds.compute()
            counts = np.bincount(ds.status.values.ravel(), minlength=len(Status))
            ds.attrs.update({"summary": finish(counts), "chain": chain})
            return ds
        write_store(ds, out, client=c, overwrite=overwrite, attrs={"summary": finish, "chain": chain})
    return xr.open_zarr(out, decode_coords="all", consolidated=False)


def _source(scene, summary: dict, role: str) -> str:
    if isinstance(scene, xr.DataArray):
        return summary.get(role, role)
    return os.fspath(scene)


def _resample(reader: WindowReader, field: xr.Dataset, method: str) -> da.Array:
    from .resample import resample

    return resample(reader, field.dx.data, field.dy.data, method=method)
