"""Scenes: open GeoTIFF/COG/Zarr as dask-backed ``(band, y, x)`` DataArrays, ingest to Zarr.

A scene is a float32 :class:`xarray.DataArray` with dims ``(band, y, x)``; nodata is NaN
(the mask), the CRS and affine transform ride along through rioxarray, and
``attrs["source"]`` names the file it came from. Pixel/world conversion lives here, with the
half-pixel offset explicit in one place.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable
from typing import Any

import dask
import numpy as np
import rioxarray  # noqa: F401  (registers the .rio accessor)
import xarray as xr
import zarr
from affine import Affine
from rasterio.errors import NotGeoreferencedWarning

from . import storage
from .chunkcache import array_identity, read_chunked
from .conventions import georeference, pixel_grid
from .errors import InputError, as_environment_failure
from .geometry import pixel_to_world, world_to_pixel  # noqa: F401  (part of this module's API)
from .outputs import check_output, commit_output, product_attrs
from .runtime import cancel_and_settle
from .tiles import Window

IMAGE_VAR = "image"


def _is_zarr(path: str) -> bool:
    p = path.rstrip("/")
    return p.endswith(".zarr") or (os.path.isdir(p) and os.path.exists(os.path.join(p, "zarr.json")))


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def is_read_error(exc: BaseException) -> bool:
    """Whether ``exc`` is GDAL/rasterio failing to decode a file (truncated, damaged), not the machine.

    An error raised on a worker may arrive as a plain ``Exception`` holding the original's
    repr (when it does not unpickle), so its text is checked too.
    """
    import rasterio.errors

    if isinstance(exc, rasterio.errors.RasterioError):
        return True
    return any(name in f"{type(exc).__name__} {exc!r}" for name in ("RasterioIOError", "RasterioError", "CPLE_"))


def _chunks(chunks: int | dict | None) -> dict:
    if isinstance(chunks, dict):
        return {"band": -1, **chunks}
    t = chunks or 512
    return {"band": -1, "y": t, "x": t}


def open_scene(
    path: str | os.PathLike,
    *,
    chunks: int | dict | None = 512,
    nodata: float | None = None,
    bands: list[int] | None = None,
    grid: bool = False,
) -> xr.DataArray:
    """Open a scene lazily as a float32 ``(band, y, x)`` DataArray with NaN as nodata.

    Parameters
    ----------
    path : str or PathLike
        A GeoTIFF/COG (anything GDAL reads) or a Zarr store written by :func:`ingest`
        (local path or fsspec URL).
    chunks : int or dict, optional
        Chunk size in y and x (the tile of the tile-parallel stages), or a dict
        ``{"y": ..., "x": ...}``; bands always form one chunk.
    nodata : float, optional
        Value to treat as nodata in addition to the file's declared nodata (some products,
        e.g. converted JPEG2000, do not declare it).
    bands : list of int, optional
        1-based band numbers to keep; default all.
    grid : bool, optional
        The scene defines an output grid (the base of a registration, a mosaic's reference,
        an ingested store), which must be north-up: a rotated geotransform is refused. Any
        other scene with a rotated geotransform is opened as not georeferenced (its place is
        then found from its pixels).

    Returns
    -------
    xarray.DataArray
        Dask-backed, dims ``(band, y, x)``, float32. ``attrs`` holds ``source`` (the path),
        ``source_dtype`` and ``georeferenced`` (whether a CRS and transform were found).

    Raises
    ------
    InputError
        If the file is missing or cannot be read as a raster.
    """
    spath = os.fspath(path)
    is_url = "://" in spath
    if not is_url and not os.path.exists(spath):
        raise InputError(spath, "no such file")
    # workers of a cluster run in other directories: they read the file by its absolute path
    where = spath if is_url else os.path.abspath(spath)
    try:
        if _is_zarr(spath):
            ds = xr.open_zarr(where, decode_coords="all", consolidated=False, chunks={})
            if IMAGE_VAR not in ds:
                raise InputError(spath, f"Zarr store has no '{IMAGE_VAR}' array (was it written by `geocoder ingest`?)")
            da = ds[IMAGE_VAR]
            if chunks:
                da = da.chunk(_chunks(chunks))
            source_dtype = da.attrs.get("source_dtype", str(da.dtype))
        else:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", NotGeoreferencedWarning)  # a raw frame, on purpose
                da = rioxarray.open_rasterio(where, masked=True, lock=False, cache=False)
            if isinstance(da, list):
                raise InputError(spath, "has several subdatasets; open one of them")
            # every chunk's task holds the file's reader itself (inline_array): as one shared
            # input it lived on one worker, and every chunk's read and store was drawn there
            # (the eight of a 2048² pair's ingest ran one after another on one of two workers);
            # the key changes with the file (storage.identity)
            token = dask.base.tokenize(storage.identity(where), chunks)
            da = da.chunk(_chunks(chunks), inline_array=True, name_prefix="open_rasterio-", token=token)
            source_dtype = str(da.encoding.get("rasterio_dtype", da.encoding.get("dtype", da.dtype)))
    except InputError:
        raise
    except Exception as exc:  # rasterio/zarr raise many types; name the file and the cause
        raise InputError(spath, f"cannot be read as a raster ({_first_line(exc)})") from exc
    if "complex" in source_dtype:
        raise InputError(spath, f"has complex pixels ({source_dtype}); write the amplitude or the real part to a real-valued raster first")
    if da.ndim != 3 or da.dims != ("band", "y", "x"):
        raise InputError(spath, f"expected dims (band, y, x), found {da.dims}")
    if bands is not None:
        bad = [b for b in bands if not 1 <= b <= da.sizes["band"]]
        if bad:
            raise InputError(spath, f"has {da.sizes['band']} band(s); band(s) {bad} do not exist")
        da = da.isel(band=[b - 1 for b in bands])
    da = da.astype(np.float32)
    if nodata is not None:
        da = da.where(da != nodata)
    crs = da.rio.crs
    transform = da.rio.transform()
    if crs is not None and not transform.is_rectilinear:
        if grid:
            raise InputError(spath, f"has a rotated geotransform ({tuple(round(v, 6) for v in transform[:6])}); geocoder's "
                                    "outputs are north-up grids: warp it north-up first (e.g. gdalwarp IN OUT.tif)")
        crs = None
        da = da.drop_vars("spatial_ref", errors="ignore")
    georef = crs is not None and not transform.is_identity and "spatial_ref" in da.coords
    if crs is None:
        # pixel index coordinates, as the conventions say (x = column, y = row)
        da = da.assign_coords(x=np.arange(da.sizes["x"], dtype=np.float64), y=np.arange(da.sizes["y"], dtype=np.float64))
    da = da.assign_coords(band=np.arange(1, da.sizes["band"] + 1))
    da.attrs = {"source": spath, "source_dtype": source_dtype, "georeferenced": bool(georef)}
    da.name = IMAGE_VAR
    if georef:
        da = da.rio.write_crs(crs).rio.write_transform(transform)
    return da


def scene_transform(scene: xr.DataArray) -> Affine | None:
    """Affine transform (pixel corner convention, as GDAL) of a georeferenced scene."""
    if not scene.attrs.get("georeferenced"):
        return None
    return scene.rio.transform()


def ingest(
    src: str | os.PathLike | xr.DataArray,
    out: str | os.PathLike,
    *,
    tile: int | None = None,
    nodata: float | None = None,
    bands: list[int] | None = None,
    client=None,
    atomic: bool = True,
    overwrite: bool = False,
) -> xr.DataArray:
    """Write a scene to a Zarr v3 store chunked by tile, CRS and transform kept.

    The store holds one array ``image`` (band, y, x), float32, NaN = nodata, chunked
    ``(bands, tile, tile)``. It is written under a temporary name and committed when
    complete (:func:`geocoder.storage.commit_store`), so a killed job never leaves a store
    that looks finished.

    Parameters
    ----------
    src : str, PathLike or xarray.DataArray
        A file :func:`open_scene` reads (GeoTIFF/COG/Zarr, path or URL), or a scene
        DataArray ``(band, y, x)`` written as it is.
    out : str or PathLike
        The store to write: a local path or any fsspec URL.
    tile : int, optional
        Chunk size in y and x. Default :func:`geocoder.get_option` ``("tile")`` (512 unless
        set by :func:`geocoder.set_options` or Dask config ``geocoder.tile``).
    nodata : float, optional
        Extra nodata value of ``src`` (see :func:`open_scene`); not used for a DataArray.
    bands : list of int, optional
        1-based bands of ``src`` to keep, default all; not used for a DataArray.
    client : distributed.Client, optional
        Where to compute the write; default Dask's current scheduler.
    atomic : bool
        True: write under a temporary name and commit when complete, after checking ``out``
        (see ``overwrite``). False writes in place without those checks, for callers that
        record completion themselves (a job's manifest): on object stores it saves copying
        the store once.
    overwrite : bool
        Replace an existing ``out`` if geocoder wrote it; without it an existing ``out``
        (other than an empty directory) is refused. Anything geocoder did not write is never
        replaced, and an ``out`` equal to, inside or containing ``src``, or equal to or
        containing the working directory, is always refused
        (:func:`geocoder.outputs.check_output`). Used only when ``atomic``.

    Returns
    -------
    xarray.DataArray
        The scene re-opened from the new store, chunked by ``tile``.

    Raises
    ------
    InputError
        If ``src`` cannot be read (missing, truncated, damaged) or ``out`` is refused.
    """
    if atomic:
        out = check_output(out, inputs=(src,), overwrite=overwrite, option="OUT")
    if tile is None:
        from .options import get_option

        tile = get_option("tile")
    scene = src if isinstance(src, xr.DataArray) else open_scene(src, chunks=tile, nodata=nodata, bands=bands, grid=True)
    out = storage.normalize(out)
    tmp = storage.temporary_sibling(out) if atomic else out
    try:
        _write_stores([scene], [tmp], [out], tile=tile, client=client)
    except BaseException:
        if atomic:
            storage.remove(tmp)
        raise
    if atomic:
        commit_output(tmp, out, overwrite=overwrite)
    return _reopen(scene, out, tile)


def ingest_scenes(scenes: list[xr.DataArray], outs: list[str], *, tile: int, client=None,
                  reduce: list[Callable[[xr.DataArray], Any] | None] | None = None) -> list[xr.DataArray]:
    """Write several scenes to their Zarr stores in one graph (:func:`ingest`'s layout), in place.

    For a job that records completion itself: the stores are written where they are named,
    without :func:`ingest`'s temporary name and checks of ``out``. All chunks of all scenes
    are one Dask computation, so the scenes are read and written in parallel.

    ``reduce`` (one per scene, or None) maps a scene's image as it is written (a lazy
    ``(band, y, x)`` float32 DataArray) to lazy figures of it (statistics, an overview) that
    are computed in the same graph, so the source is read once for both; their values are
    the ``attrs["reduced"]`` of the returned scene.

    Returns the scenes re-opened from their stores, chunked by ``tile``.

    Raises
    ------
    InputError
        If a scene cannot be read (named).
    """
    outs = [storage.normalize(o) for o in outs]
    values = _write_stores(scenes, outs, outs, tile=tile, client=client, reduce=reduce)
    reopened = [_reopen(scene, out, tile) for scene, out in zip(scenes, outs)]
    for scene, value, f in zip(reopened, values, reduce or [None] * len(scenes)):
        if f is not None:
            scene.attrs["reduced"] = value
    return reopened


def _reopen(scene: xr.DataArray, out: str, tile: int) -> xr.DataArray:
    reopened = open_scene(out, chunks=tile)
    reopened.attrs["source"] = scene.attrs.get("source", out)
    return reopened


def _scene_dataset(scene: xr.DataArray, tile: int) -> xr.Dataset:
    """A scene as the dataset of an ingested store: ``image`` chunked by tile, its attributes, its grid."""
    scene = scene.chunk(_chunks(tile))
    ds = scene.to_dataset(name=IMAGE_VAR)
    ds.attrs.update(product_attrs("scene"))
    ds[IMAGE_VAR].attrs = {k: v for k, v in scene.attrs.items() if k != "georeferenced"}
    # a DataArray not made by open_scene (rioxarray's own) counts as georeferenced by its CRS
    georeferenced = bool(scene.attrs.get("georeferenced", scene.rio.crs is not None))
    ds[IMAGE_VAR].attrs["georeferenced"] = int(georeferenced)
    ds[IMAGE_VAR].attrs.setdefault("long_name", "scene bands, NaN where nodata")
    ds[IMAGE_VAR].encoding = {}
    ds["band"].attrs["long_name"] = "band of the source (1-based)"
    if georeferenced:
        return georeference(ds, scene.rio.crs, scene.rio.transform())
    return pixel_grid(ds)


def _write_stores(scenes: list[xr.DataArray], paths: list[str], outs: list[str], *, tile: int, client=None,
                  reduce: list[Callable[[xr.DataArray], Any] | None] | None = None) -> list:
    """Write every scene to its path in one computation; errors name the scene (or ``outs``' store).

    Returns ``reduce[i]`` of every scene's written image, computed in the same graph (None
    where there is none).
    """
    datasets = [_scene_dataset(scene, tile) for scene in scenes]
    reduce = reduce or [None] * len(scenes)
    # one delayed per scene: its write and its reductions, computed in one graph, so they share the reads
    delayed = [dask.delayed(_written_and_reduced, pure=False)(
        ds.to_zarr(path, mode="w", zarr_format=3, consolidated=False, compute=False, encoding=storage.encoding(ds)), None if f is None else f(ds[IMAGE_VAR]))
        for ds, path, f in zip(datasets, paths, reduce)]
    if client is not None:
        futures = client.compute(delayed)
        results = [(f, None) for f in futures]
    else:
        results = [(None, d) for d in delayed]
    values = []
    done = False
    try:
        for (future, task), scene, out in zip(results, scenes, outs):
            try:
                values.append(future.result() if future is not None else task.compute())
            except Exception as exc:
                failure = as_environment_failure(exc, out)
                if failure is not None:
                    raise failure from exc
                if is_read_error(exc):
                    raise InputError(scene.attrs.get("source", "input"),
                                     f"cannot be read, the file is truncated or damaged ({_first_line(exc)})") from exc
                raise
        done = True
    finally:
        if client is not None and not done:  # the other stores' tasks may still be writing
            cancel_and_settle(client, [f for f, _ in results], delayed)
    return values


def _written_and_reduced(written: Any, reduced: Any) -> Any:
    return reduced


class WindowReader:
    """Pickleable, lazy reader of windows of a scene's Zarr ``image`` array.

    Tasks on workers call :meth:`read` to fetch exactly the window they need. The store
    must not change while it is read: windows of a local store come through the worker's
    cache of decoded chunks (:mod:`geocoder.chunkcache`), which the job's tiles share.
    """

    def __init__(self, store: str, variable: str = IMAGE_VAR) -> None:
        self.store = os.fspath(store)
        self.variable = variable
        self._array = None
        self._identity = None

    def __getstate__(self):
        return {"store": self.store, "variable": self.variable}

    def __setstate__(self, state):
        self.store, self.variable, self._array, self._identity = state["store"], state["variable"], None, None

    @property
    def array(self) -> zarr.Array:
        if self._array is None:
            try:  # `geocoder ingest` writes Zarr v3; opened once per process (storage.open_array)
                self._array = storage.open_array(self.store, self.variable)
            except FileNotFoundError:
                self._array = zarr.open_group(self.store, mode="r")[self.variable]
            self._identity = array_identity(self.store, self.variable)
        return self._array

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.array.shape)

    def sample(self, x: np.ndarray, y: np.ndarray, *, method: str) -> np.ndarray:
        """All bands at pixel positions ``(x, y)``, reading only the window they need.

        Returns float32 ``(bands, *x.shape)``, NaN where the image has no data.
        """
        from .kernels.resample import sample, window_for

        win = window_for(x, y, method=method, shape=self.shape[1:])
        if win is None:
            return np.full((self.shape[0], *np.shape(x)), np.nan, dtype=np.float32)
        r0, r1, c0, c1 = win
        return sample(self.read(r0, r1, c0, c1), x - c0, y - r0, method=method)

    def read(self, row0: int, row1: int, col0: int, col1: int) -> np.ndarray:
        """Window ``[:, row0:row1, col0:col1]`` clipped to the array; float32, NaN outside."""
        _, h, w = self.shape
        out = np.full((self.shape[0], row1 - row0, col1 - col0), np.nan, dtype=np.float32)
        r0, r1, c0, c1 = Window(row0, row1, col0, col1).clip(h, w)
        if r1 > r0 and c1 > c0:
            part = out[:, r0 - row0 : r1 - row0, c0 - col0 : c1 - col0]
            array = self.array
            if self._identity is None:
                part[:] = array[:, r0:r1, c0:c1]
            else:
                read_chunked(self._identity, array.shape, array.chunks, array.__getitem__, (r0, r1, c0, c1), part)
        return out


def write_geotiff(
    path: str | os.PathLike,
    array: np.ndarray,
    *,
    transform: Affine | None = None,
    crs: str | None = None,
    nodata: float | None = None,
    dtype: str | None = None,
) -> None:
    """Write a ``(band, y, x)`` or ``(y, x)`` array as a tiled, deflate-compressed GeoTIFF.

    Without ``transform`` and ``crs`` the file is a raw (not georeferenced) image.
    """
    import rasterio

    data = np.asarray(array)
    if data.ndim == 2:
        data = data[None]
    dtype = dtype or str(data.dtype)
    if np.issubdtype(np.dtype(dtype), np.integer):
        info = np.iinfo(dtype)
        data = np.clip(np.rint(np.nan_to_num(data, nan=nodata if nodata is not None else 0)), info.min, info.max)
    profile = {
        "driver": "GTiff", "width": data.shape[2], "height": data.shape[1], "count": data.shape[0],
        "dtype": dtype, "tiled": True, "blockxsize": 256, "blockysize": 256, "compress": "deflate",
    }
    if transform is not None:
        profile["transform"] = transform
    if crs is not None:
        profile["crs"] = crs
    if nodata is not None:
        profile["nodata"] = nodata
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)  # a raw image, on purpose
        with rasterio.open(os.fspath(path), "w", **profile) as dst:
            dst.write(data.astype(dtype))
