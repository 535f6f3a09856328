"""What the registration report reads: a register output (store or dataset), its overview level,
full-resolution windows, the per-line reductions, the input images and a truth field.

Nothing here loads a scene whole: maps come from the finest overview level whose larger side
is at most ``max_size``; per-line means and the sigma calibration are Dask reductions over the
full-resolution arrays (on the current Dask scheduler); the HSI check and the grey-level
statistics read full-resolution windows.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field

import dask
import dask.array as da
import numpy as np
import xarray as xr

from ..errors import InputError
from ..kernels.polynomial import PolyMap
from ..status import Status
from .analysis import polynomial_grid

#: Status codes by name, as the store's ``status`` attributes declare them.
_CODES = len(Status)


@dataclass
class Source:
    """A register output opened for the report.

    Attributes
    ----------
    root : xarray.Dataset
        The full-resolution dataset (lazy).
    level : xarray.Dataset
        The overview level the maps show (lazy; the root for a small scene).
    factor : int
        Full-resolution pixels per level pixel (on each side).
    location : str or None
        The store (None for a dataset in memory).
    summary : dict
        The ``summary`` attribute (JSON decoded).
    mapping : PolyMap or None
        The global polynomial (``mapping`` attribute).
    tiepoints : xarray.Dataset or None
        The tie points.
    legend : dict
        Status code -> name, from the ``status`` variable's ``flag_values``/``flag_meanings``.

    Parameters
    ----------
    root, level, factor, location, summary, mapping, tiepoints, legend
        As the attributes.
    """

    root: xr.Dataset
    level: xr.Dataset
    factor: int
    location: str | None
    summary: dict
    mapping: PolyMap | None
    tiepoints: xr.Dataset | None
    legend: dict = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        """Full-resolution ``(rows, columns)``."""
        return self.root.sizes["y"], self.root.sizes["x"]

    def level_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Full-resolution coordinates of the level's pixel centres.

        Returns
        -------
        tuple of numpy.ndarray
            ``(x, y)``, 1-D each.
        """
        f = self.factor
        return (np.arange(self.level.sizes["x"]) * f + (f - 1) / 2.0,
                np.arange(self.level.sizes["y"]) * f + (f - 1) / 2.0)


def _coarsen(ds: xr.Dataset, factor: int) -> xr.Dataset:
    """A dataset on a grid ``factor`` times coarser: means of floats, the top-left pixel of integers."""
    out = {}
    for name, var in ds.data_vars.items():
        if not {"y", "x"} <= set(var.dims):
            continue
        if np.issubdtype(var.dtype, np.floating):
            out[name] = var.coarsen(y=factor, x=factor, boundary="pad").mean()
        else:
            out[name] = var.isel(y=slice(None, None, factor), x=slice(None, None, factor))
    # coarsened and strided coordinates differ: drop them, or the variables would be aligned apart
    return xr.Dataset({k: v.reset_coords(drop=True).drop_vars(["x", "y"], errors="ignore") for k, v in out.items()})


def _legend(status: xr.DataArray | None) -> dict[int, str]:
    if status is None:
        return {}
    values = status.attrs.get("flag_values")
    names = status.attrs.get("flag_meanings")
    if values is None or not names:
        return {int(s): s.name.lower() for s in Status}
    return {int(v): n for v, n in zip(np.atleast_1d(values), str(names).split())}


def open_source(source, *, max_size: int = 1500) -> Source:
    """Open a register output for the report, and pick the overview level the maps show.

    Parameters
    ----------
    source : str, PathLike or xarray.Dataset
        A register Zarr store, or the dataset :func:`geocoder.register` returned.
    max_size : int
        Largest side (pixels) of the maps: the finest overview level at most this large (a
        dataset in memory is averaged down by a power of two instead).

    Returns
    -------
    Source

    Raises
    ------
    InputError
        If ``source`` is not a register output.
    """
    location = None
    if isinstance(source, xr.Dataset):
        root = source
    else:
        location = os.fspath(source)
        try:
            root = xr.open_zarr(location, consolidated=False)
        except (FileNotFoundError, ValueError, KeyError, OSError) as exc:
            raise InputError(location, f"cannot be opened as a Zarr store ({type(exc).__name__}: {exc})") from None
    if "summary" not in root.attrs or "dx" not in root:
        raise InputError(location or "dataset", "is not a register output (no summary attribute or dx variable)")
    summary = json.loads(root.attrs["summary"])
    mapping = PolyMap.from_dict(json.loads(root.attrs["mapping"])) if "mapping" in root.attrs else None
    h, w = root.sizes["y"], root.sizes["x"]
    level, factor = root, 1
    layout = (root.attrs.get("multiscales") or {}).get("layout", []) if location else []
    for k, item in enumerate(layout):
        shape = item.get("spatial:shape") or [math.ceil(h / 2**k), math.ceil(w / 2**k)]
        if max(shape) <= max_size:
            if k:
                level = xr.open_zarr(location, group=item["asset"], consolidated=False)
            factor = 2**k
            break
    else:
        while max(h, w) / factor > max_size:
            factor *= 2
        if factor > 1:
            level = _coarsen(root, factor)
    tiepoints = None
    if location is not None:
        try:
            tiepoints = xr.open_zarr(location, group="tiepoints", consolidated=False)
        except (FileNotFoundError, KeyError, ValueError, OSError):
            tiepoints = None
    elif isinstance(root.attrs.get("tiepoints"), xr.Dataset):
        tiepoints = root.attrs["tiepoints"]
    return Source(root, level, factor, location, summary, mapping, tiepoints, _legend(root.get("status")))


def level_polynomial(src: Source) -> tuple[np.ndarray, np.ndarray] | None:
    """The polynomial displacement at the level's pixel centres.

    Parameters
    ----------
    src : Source
        The opened output.

    Returns
    -------
    tuple of numpy.ndarray or None
        ``(dx, dy)`` on the level grid; None when the store has no mapping.
    """
    if src.mapping is None:
        return None
    x, y = src.level_centres()
    return polynomial_grid(src.mapping, x, y)


def _line_block(dx, dy, status, sx, sy, block_info=None, *, mapping: PolyMap, matched: int):
    (r0, r1), (c0, c1) = block_info[0]["array-location"]
    px, py = polynomial_grid(mapping, np.arange(c0, c1), np.arange(r0, r1))
    ok = (status == matched) & np.isfinite(dx) & np.isfinite(dy)
    ok_sigma = ok & np.isfinite(sx) & np.isfinite(sy)
    out = np.stack([
        np.where(ok, dx - px, 0.0).sum(axis=1), np.where(ok, dy - py, 0.0).sum(axis=1), ok.sum(axis=1),
        np.where(ok_sigma, sx.astype(np.float64) ** 2, 0.0).sum(axis=1),
        np.where(ok_sigma, sy.astype(np.float64) ** 2, 0.0).sum(axis=1), ok_sigma.sum(axis=1),
    ], axis=-1)
    return out[:, None, :]


def line_sums(src: Source) -> np.ndarray | None:
    """Per full-resolution row, sums over the matched pixels of the displacement after the polynomial.

    One Dask reduction over the full-resolution arrays (one small task per chunk).

    Parameters
    ----------
    src : Source
        The opened output.

    Returns
    -------
    numpy.ndarray or None
        Shape ``(rows, 6)``: sums of ``dx - poly`` and ``dy - poly``, their number, sums of
        ``sigma_x^2`` and ``sigma_y^2``, and the number with a sigma. None when the store has
        no sigma (``--no-dense``) or no polynomial.
    """
    r = src.root
    if src.mapping is None or "sigma_x" not in r or "sigma_y" not in r:
        return None
    arrays = [r[n].data if isinstance(r[n].data, da.Array) else da.from_array(r[n].values, chunks=512)
              for n in ("dx", "dy", "status", "sigma_x", "sigma_y")]
    arrays = [a.rechunk(arrays[0].chunks) for a in arrays]
    nbx = len(arrays[0].chunks[1])
    blocks = da.map_blocks(_line_block, *arrays, mapping=src.mapping, matched=int(Status.MATCHED), dtype=np.float64,
                           chunks=(arrays[0].chunks[0], (1,) * nbx, (6,)), new_axis=2)
    return np.asarray(blocks.sum(axis=1).compute())


def _status_block(status, ex, ey, sx, sy) -> np.ndarray:
    ok = np.isfinite(ex) & np.isfinite(ey)
    ok_sigma = ok & np.isfinite(sx) & np.isfinite(sy)
    s = status.ravel().astype(np.intp)

    def count(weights, mask):
        return np.bincount(s, weights=np.where(mask, weights, 0.0).ravel(), minlength=_CODES)[:_CODES]

    return np.stack([count(1.0, ok), count(ex.astype(np.float64) ** 2, ok), count(ey.astype(np.float64) ** 2, ok),
                     count(1.0, ok_sigma), count(sx.astype(np.float64) ** 2, ok_sigma),
                     count(sy.astype(np.float64) ** 2, ok_sigma)])


def status_sums(src: Source, truth: tuple[da.Array, da.Array]) -> np.ndarray:
    """Per status code, sums of squared errors against the truth and of squared sigma.

    A Dask reduction over the full-resolution arrays (one task per chunk).

    Parameters
    ----------
    src : Source
        The opened output.
    truth : tuple of dask.array.Array
        ``(dx, dy)`` of the truth at full resolution.

    Returns
    -------
    numpy.ndarray
        Shape ``(6, codes)``: pixels with an error, sums of squared errors in x and y, pixels
        with a sigma, sums of ``sigma_x^2`` and ``sigma_y^2``.
    """
    r = src.root
    dx, dy, status = (r[n].data for n in ("dx", "dy", "status"))
    dx, dy, status = (a if isinstance(a, da.Array) else da.from_array(a, chunks=512) for a in (dx, dy, status))
    chunks = dx.chunks
    if "sigma_x" in r:
        sx, sy = (da.asarray(r[n].data).rechunk(chunks) for n in ("sigma_x", "sigma_y"))
    else:
        sx = sy = da.full(dx.shape, np.nan, chunks=chunks, dtype=np.float32)
    tx, ty = (t.rechunk(chunks) for t in truth)
    ex, ey = dx - tx, dy - ty
    parts = [dask.delayed(_status_block)(*b) for b in zip(*(a.to_delayed().ravel() for a in
                                                             (status.rechunk(chunks), ex, ey, sx, sy)))]
    return np.sum(dask.compute(*parts), axis=0)


def window(var: xr.DataArray, rows: tuple[int, int], cols: tuple[int, int]) -> np.ndarray:
    """A full-resolution window of a ``(y, x)`` or ``(band, y, x)`` variable.

    Parameters
    ----------
    var : xarray.DataArray
        The variable (lazy).
    rows, cols : tuple of int
        Half-open ranges ``(start, stop)``.

    Returns
    -------
    numpy.ndarray
        float64.
    """
    return np.asarray(var.isel(y=slice(*rows), x=slice(*cols)).values, dtype=np.float64)


def open_image(path: str | None, *, band: int):
    """One band of an input image, lazily, or None with the reason it cannot be read.

    Parameters
    ----------
    path : str or None
        The image (GeoTIFF/COG/Zarr).
    band : int
        1-based band.

    Returns
    -------
    tuple
        ``(DataArray (y, x) or None, problem or None)``.
    """
    from ..scene import open_scene

    if not path:
        return None, "its path is not recorded"
    if not os.path.exists(path) and "://" not in str(path):
        return None, f"{path} does not exist (moved or deleted since the registration?)"
    import warnings

    try:
        with warnings.catch_warnings():  # a raw scanner image has no georeference, and needs none here
            warnings.filterwarnings("ignore", message=".*no geotransform.*")
            scene = open_scene(path)
    except Exception as exc:  # noqa: BLE001  (any reader failure: the section says why it is missing)
        return None, f"{path} cannot be read ({type(exc).__name__}: {exc})"
    if not 1 <= band <= scene.sizes["band"]:
        return None, f"{path} has no band {band}"
    return scene.isel(band=band - 1), None


def read_truth(truth, src: Source) -> tuple[tuple[da.Array, da.Array], str]:
    """The true displacement on the base grid at full resolution, lazy, and a description.

    ``truth`` is a ``(dx, dy)`` pair of arrays on the base grid, or a Zarr store holding
    ``dx`` and ``dy`` (a truth store, or another register output), or the store that
    ``geocoder simulate`` wrote (``ground_x``/``ground_y`` per pixel of the simulated image,
    in the CRS of the ortho that is the base): its pixels are placed on the base grid by the
    register output's transform and the truth is interpolated between them.

    Parameters
    ----------
    truth : str, PathLike or (array, array)
        The truth, as above.
    src : Source
        The opened output (its grid).

    Returns
    -------
    tuple
        ``((dx, dy), description)``: dask arrays (float64) chunked like the output's ``dx``.
    """
    h, w = src.shape
    chunks = src.root["dx"].data.chunks if isinstance(src.root["dx"].data, da.Array) else (512, 512)
    if isinstance(truth, (tuple, list)) and len(truth) == 2:
        parts = [da.asarray(t) if isinstance(t, da.Array) else da.from_array(np.asarray(t, dtype=np.float64), chunks=chunks)
                 for t in truth]
        where = "the given (dx, dy) arrays"
    else:
        location = os.fspath(truth)
        try:
            ds = xr.open_zarr(location, consolidated=False)
        except (FileNotFoundError, ValueError, KeyError, OSError) as exc:
            raise InputError(location, f"cannot be opened as a truth store ({type(exc).__name__}: {exc})") from None
        if "dx" in ds and "dy" in ds:
            parts = [ds["dx"].data, ds["dy"].data]
            where = f"dx/dy of {location}"
        elif "ground_x" in ds and "ground_y" in ds:
            parts = list(_truth_from_simulation(ds, src))
            where = f"the simulated image's ground coordinates in {location}"
        else:
            raise InputError(location, "holds neither dx/dy nor the ground_x/ground_y of 'geocoder simulate'")
    for p in parts:
        if p.shape != (h, w):
            raise InputError(where, f"truth is {p.shape[1]} x {p.shape[0]} px, the registration {w} x {h} px")
    return (parts[0].astype(np.float64).rechunk(chunks), parts[1].astype(np.float64).rechunk(chunks)), where


#: Largest base grid (pixels) on which a simulated image's ground coordinates are gridded as truth.
MAX_SIMULATED_PIXELS = 4096 * 4096
#: Most scattered points of a simulated image used for the gridding (its pixels are thinned to this).
MAX_SCATTERED = 1_000_000


def _truth_from_simulation(ds: xr.Dataset, src: Source) -> tuple[da.Array, da.Array]:
    """Base-grid truth from a simulated image's per-pixel ground coordinates (scattered -> grid)."""
    from scipy.interpolate import LinearNDInterpolator

    from ..geometry import world_to_pixel

    if "spatial:transform" not in src.root.attrs:
        raise InputError(src.location or "dataset", "has no georeference: a simulated truth cannot be placed on its grid")
    from affine import Affine

    transform = Affine(*src.root.attrs["spatial:transform"][:6])
    hs, ws = ds.sizes["y"], ds.sizes["x"]
    h, w = src.shape
    if h * w > MAX_SIMULATED_PIXELS:
        raise InputError("truth", f"the base grid ({w} x {h} px) is too large to grid a simulated truth on; "
                                  "give the truth as dx/dy")
    step = max(1, math.ceil(math.sqrt(hs * ws / MAX_SCATTERED)))  # a smooth field: thinned pixels suffice
    gx = np.asarray(ds["ground_x"][::step, ::step].values, dtype=np.float64)
    gy = np.asarray(ds["ground_y"][::step, ::step].values, dtype=np.float64)
    qy, qx = (np.mgrid[0:hs:step, 0:ws:step]).astype(np.float64)
    px, py = world_to_pixel(transform, gx, gy)
    ok = np.isfinite(px) & np.isfinite(py)
    interp = LinearNDInterpolator(np.column_stack([px[ok], py[ok]]), np.column_stack([(qx - px)[ok], (qy - py)[ok]]))
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    d = interp(xx.ravel(), yy.ravel()).reshape(h, w, 2)
    return da.from_array(d[..., 0], chunks=512), da.from_array(d[..., 1], chunks=512)
