"""Cloud-Optimized GeoTIFF export, tile-parallel on Dask.

:func:`to_cog` writes one variable of a geocoder output (or any georeferenced, dask-backed
DataArray) as a COG:

* every output tile of every level is one task that computes and compresses it on a worker;
  only the compressed bytes travel to the client, which appends them to a spill file next to
  the output as they arrive (client memory: one tile);
* overviews halve the resolution level by level, from the full-resolution data: averages carry
  a per-pixel ``(sum, count)`` pair up the pyramid, so every overview pixel is the exact mean of
  the valid full-resolution pixels it covers while a task reads at most 2 x 2 blocks of the
  level below; integer data (status codes) take the nearest pixel, the top-left one of the
  covered block (full-resolution pixel ``(i * f, j * f)`` at factor ``f``);
* the client then writes the file in GDAL's COG layout: header, the ghost area
  (``GDAL_STRUCTURAL_METADATA``), the IFDs of all levels (full resolution first, overviews
  flagged reduced-resolution, largest to smallest), then the tile data of the smallest overview
  first and of the full resolution last, row-major within a level, each tile with GDAL's
  4-byte size leader and 4-byte trailer; BigTIFF when the file would not fit in 4 GiB;
* bands are interleaved by pixel (``PlanarConfiguration = 1``), as GDAL's COG driver does by
  default; float nodata is NaN unless ``nodata`` says otherwise (``GDAL_NODATA`` tag);
* the GeoTIFF tags (GeoKeyDirectory and its parameters, ModelPixelScale/ModelTiepoint or
  ModelTransformation) are the ones GDAL itself writes for the CRS and transform: a 1 x 1
  GeoTIFF is written in memory by rasterio and its tags are copied, so EPSG codes,
  WKT-only CRSs and rotated transforms come out exactly as GDAL would write them.

Why the TIFF structure is written here (``struct`` + ``zlib``) rather than with ``tifffile``:
``tifffile`` is not a dependency of the project, and a COG's constraints (IFDs of all levels
before the data, the smallest overview's tiles first, GDAL's ghost area, tile leaders) are
about byte order in the file, which is simplest to get exactly right when the writer places
every byte itself; the TIFF part is ~150 lines. GDAL's COG driver is not used because it
computes the tiles in one process. That writer, the overview levels it streams and the tile
tasks are why the module is over 500 lines.

The file is written under a hidden temporary name next to the output and renamed into place
when complete (:func:`geocoder.outputs.commit_output`); an existing output is replaced only
with ``overwrite`` and only if geocoder wrote it (its ``GDAL_METADATA`` names the product).
"""

from __future__ import annotations

import math
import os
import struct
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path

import dask
import dask.array as da
import numpy as np
import rioxarray  # noqa: F401  (registers the .rio accessor this module reads the georeference with)
import xarray as xr

from . import progress, storage
from .errors import GeocoderWarning, InputError, as_environment_failure
from .outputs import check_output, commit_output, product_attrs

__all__ = ["to_cog"]

#: The product name a COG carries in its GDAL metadata (see :func:`geocoder.outputs.product_of`).
PRODUCT = "cog"

_COMPRESSION = {"none": 1, "deflate": 8}
_GEO_TAGS = (33550, 33922, 34264, 34735, 34736, 34737)  # pixel scale, tiepoint, transformation, geokeys
# TIFF field types: code -> numpy dtype (little-endian) of one value
_TYPES = {1: "u1", 2: "u1", 3: "<u2", 4: "<u4", 5: "<u4", 6: "i1", 7: "u1", 8: "<i2", 9: "<i4", 10: "<i4",
          11: "<f4", 12: "<f8", 16: "<u8", 17: "<i8", 18: "<u8"}
_SHORT, _LONG, _ASCII, _DOUBLE, _LONG8 = 3, 4, 2, 12, 16


@dataclass(frozen=True)
class _TileSpec:
    """How a worker turns one block into the bytes of one TIFF tile (small, pickled with each task)."""

    blocksize: int
    dtype: str
    fill: float
    nodata: float | None
    compression: str
    predictor: int
    level: int
    average: bool


# ---------------------------------------------------------------------------- worker side


def _accumulate(block: np.ndarray, nodata: float | None) -> np.ndarray:
    """``(2, band, y, x)`` float64: the sum of the valid pixels and their count (full resolution)."""
    values = block.astype(np.float64)
    valid = ~np.isnan(values)
    if nodata is not None and not math.isnan(nodata):
        valid &= values != nodata
    return np.stack([np.where(valid, values, 0.0), valid.astype(np.float64)])


def _halve(block: np.ndarray) -> np.ndarray:
    """Sum ``(sum, count)`` over 2 x 2 pixels (the block's sides are even)."""
    n, b, h, w = block.shape
    return block.reshape(n, b, h // 2, 2, w // 2, 2).sum(axis=(3, 5))


def _predict(tile: np.ndarray, predictor: int) -> bytes:
    """The tile ``(y, x, band)`` as TIFF bytes after the predictor (1 none, 2 horizontal, 3 floating point)."""
    rows, cols, bands = tile.shape
    if predictor == 1:
        return tile.astype(tile.dtype.newbyteorder("<"), copy=False).tobytes()
    if predictor == 2:
        line = tile.astype(tile.dtype.newbyteorder("<")).reshape(rows, cols * bands)
        line[:, bands:] = line[:, bands:] - line[:, :-bands]  # integer arithmetic wraps, as libtiff's
        return line.tobytes()
    # floating point predictor (Adobe TIFF Technical Note 3): per row, the big-endian bytes
    # of the samples regrouped by significance, then byte differences with a stride of one pixel
    size = tile.dtype.itemsize
    raw = tile.astype(tile.dtype.newbyteorder(">")).view(np.uint8).reshape(rows, cols * bands, size)
    planes = np.ascontiguousarray(raw.transpose(0, 2, 1)).reshape(rows, size * cols * bands)
    planes[:, bands:] = planes[:, bands:] - planes[:, :-bands]
    return planes.tobytes()


def _encode(block: np.ndarray, spec: _TileSpec) -> bytes:
    """One block of a level (values, or ``(sum, count)`` for averaged overviews) as a compressed TIFF tile."""
    if spec.average and spec.level > 0:
        total, count = block[0], block[1]
        with np.errstate(invalid="ignore", divide="ignore"):
            values = np.where(count > 0, total / count, spec.fill)
    else:
        values = block
        if spec.nodata is not None and np.issubdtype(values.dtype, np.floating):
            values = np.where(np.isnan(values), spec.fill, values)
    dtype = np.dtype(spec.dtype)
    if np.issubdtype(dtype, np.integer) and not np.issubdtype(values.dtype, np.integer):
        info = np.iinfo(dtype)
        values = np.clip(np.rint(values), info.min, info.max)
    bands, h, w = values.shape
    bs = spec.blocksize
    tile = np.full((bs, bs, bands), spec.fill, dtype=dtype)
    tile[:h, :w] = np.moveaxis(values, 0, -1)
    raw = _predict(tile, spec.predictor)
    return zlib.compress(raw, 6) if spec.compression == "deflate" else raw


# ---------------------------------------------------------------------------- TIFF structure


@dataclass(frozen=True)
class _Entry:
    tag: int
    type: int
    count: int
    data: bytes  # little-endian values


def _entry(tag: int, type_: int, values) -> _Entry:
    if type_ == _ASCII:
        data = (values if isinstance(values, bytes) else str(values).encode("ascii")) + b"\0"
        return _Entry(tag, type_, len(data), data)
    arr = np.atleast_1d(np.asarray(values)).astype(_TYPES[type_])
    count = arr.size // 2 if type_ in (5, 10) else arr.size
    return _Entry(tag, type_, count, arr.tobytes())


def _ifd(entries: list[_Entry], start: int, next_ifd: int, big: bool) -> bytes:
    """An IFD at file offset ``start`` with its out-of-line values right after it."""
    entries = sorted(entries, key=lambda e: e.tag)
    inline = 8 if big else 4
    head = struct.pack("<Q" if big else "<H", len(entries))
    size = len(head) + len(entries) * (20 if big else 12) + (8 if big else 4)
    extra = bytearray()
    body = bytearray()
    for e in entries:
        if len(e.data) <= inline:
            value = e.data.ljust(inline, b"\0")
        else:
            value = struct.pack("<Q" if big else "<I", start + size + len(extra))
            extra += e.data + b"\0" * (len(e.data) % 2)  # values start on a word boundary
        body += struct.pack("<HHQ" if big else "<HHI", e.tag, e.type, e.count) + value
    return head + bytes(body) + struct.pack("<Q" if big else "<I", next_ifd) + bytes(extra)


def _ghost() -> bytes:
    """GDAL's structural metadata: the layout promises a reader may rely on."""
    body = ("LAYOUT=IFDS_BEFORE_DATA\nBLOCK_ORDER=ROW_MAJOR\nBLOCK_LEADER=SIZE_AS_UINT4\n"
            "BLOCK_TRAILER=LAST_4_BYTES_REPEATED\nKNOWN_INCOMPATIBLE_EDITION=NO\n ")
    return f"GDAL_STRUCTURAL_METADATA_SIZE={len(body):06d} bytes\n{body}".encode("ascii")


def _read_tags(raw: bytes) -> dict[int, tuple[int, np.ndarray]]:
    """Tags of the first IFD of a small TIFF in memory: code -> (type, values)."""
    order = "<" if raw[:2] == b"II" else ">"
    big = struct.unpack(order + "H", raw[2:4])[0] == 43
    if big:
        (ifd,) = struct.unpack(order + "Q", raw[8:16])
        (n,) = struct.unpack(order + "Q", raw[ifd : ifd + 8])
        pos, fmt, entry, inline = ifd + 8, "HHQ", 20, 8
    else:
        (ifd,) = struct.unpack(order + "I", raw[4:8])
        (n,) = struct.unpack(order + "H", raw[ifd : ifd + 2])
        pos, fmt, entry, inline = ifd + 2, "HHI", 12, 4
    tags = {}
    for k in range(n):
        at = pos + k * entry
        tag, type_, count = struct.unpack(order + fmt, raw[at : at + entry - inline])
        dtype = np.dtype(_TYPES[type_]).newbyteorder(order)
        nbytes = count * dtype.itemsize * (2 if type_ in (5, 10) else 1)
        where = at + entry - inline
        if nbytes > inline:
            (where,) = struct.unpack(order + ("Q" if big else "I"), raw[where : where + inline])
        tags[tag] = (type_, np.frombuffer(raw[where : where + nbytes], dtype=dtype))
    return tags


def _geotags(crs, transform) -> list[_Entry]:
    """The GeoTIFF tags GDAL writes for ``crs`` and ``transform`` (from a 1 x 1 GeoTIFF in memory)."""
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    with warnings.catch_warnings():
        # a CRS with an identity transform (a raw frame given a CRS) is written as such on purpose
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.MemoryFile() as mem:
            with mem.open(driver="GTiff", width=1, height=1, count=1, dtype="uint8", crs=crs, transform=transform) as d:
                d.write(np.zeros((1, 1, 1), np.uint8))
            raw = mem.read()
    tags = _read_tags(raw)
    out = []
    for tag in _GEO_TAGS:
        if tag in tags:
            type_, values = tags[tag]
            out.append(_entry(tag, type_, values.tobytes().rstrip(b"\0") if type_ == _ASCII else values))
    return out


def _metadata_xml(items: dict[str, str]) -> str:
    from xml.sax.saxutils import escape, quoteattr

    lines = "".join(f"  <Item name={quoteattr(k)}>{escape(v)}</Item>\n" for k, v in items.items())
    return f"<GDALMetadata>\n{lines}</GDALMetadata>"


def _nodata_text(nodata: float, dtype: np.dtype) -> str:
    if math.isnan(nodata):
        return "nan"
    return str(int(nodata)) if np.issubdtype(dtype, np.integer) else repr(float(nodata))


# ---------------------------------------------------------------------------- the export


def _open_source(source, variable: str | None) -> tuple[xr.DataArray, str | None]:
    """The variable to export, and the store it came from (None for an in-memory source)."""
    where = None
    name = "the dataset"
    if isinstance(source, (str, os.PathLike)):
        where = storage.normalize(source)
        name = where
        if not storage.exists(where):
            raise InputError(where, "no such Zarr store")
        if not storage.is_store(where):
            raise InputError(where, "is not a Zarr store (export reads the stores geocoder writes)")
        try:
            source = xr.open_zarr(where, decode_coords="all", consolidated=False)
        except Exception as exc:  # zarr raises many types; name the store and the cause
            raise InputError(where, f"cannot be read as a Zarr store ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from exc
    if isinstance(source, xr.Dataset):
        images = sorted(k for k, v in source.data_vars.items() if v.ndim in (2, 3) and v.dims[-2:] == ("y", "x"))
        if variable is None:
            if len(images) != 1:
                raise InputError(name, f"has {len(images)} image variables; choose one with --var: {', '.join(images) or 'none'}")
            variable = images[0]
        if variable not in images:
            raise InputError(name, f"has no image variable '{variable}'; it has: {', '.join(images) or 'none'}")
        source = source[variable]
    if not isinstance(source, xr.DataArray):
        raise TypeError(f"source must be a DataArray, a Dataset or the path of a Zarr store, not {type(source).__name__}")
    if source.ndim not in (2, 3) or source.dims[-2:] != ("y", "x"):
        raise InputError(name, f"expected dims (y, x) or (band, y, x), found {source.dims}")
    return source, where


def _levels(width: int, height: int, blocksize: int, overviews: int | None) -> int:
    """Number of overview levels: as asked, else halve until the smallest level fits one block."""
    if overviews is not None:
        if overviews < 0:
            raise ValueError(f"overviews must be 0 or more, not {overviews}")
        return int(overviews)
    n = 0
    while max(width, height) > blocksize:
        width, height, n = -(-width // 2), -(-height // 2), n + 1
    return n


def _tiff_dtype(dtype: np.dtype) -> np.dtype:
    if dtype == np.bool_:
        return np.dtype(np.uint8)
    if dtype == np.float16:
        return np.dtype(np.float32)
    if dtype.kind not in "uif":
        raise ValueError(f"cannot write {dtype} pixels to a GeoTIFF")
    return dtype


def to_cog(
    source: xr.DataArray | xr.Dataset | str | os.PathLike,
    path: str | os.PathLike,
    *,
    variable: str | None = None,
    client=None,
    scheduler: str | None = None,
    blocksize: int = 512,
    overviews: int | None = None,
    resampling: str | None = None,
    compression: str = "deflate",
    predictor: int | None = None,
    nodata: float | None = None,
    bigtiff: bool | None = None,
    overwrite: bool = False,
) -> Path:
    """Write a dask-backed image as a Cloud-Optimized GeoTIFF, every tile computed on the workers.

    Parameters
    ----------
    source : xarray.DataArray, xarray.Dataset, str or PathLike
        A ``(y, x)`` or ``(band, y, x)`` DataArray (CRS and transform through rioxarray), a
        Dataset holding one, or the path (or fsspec URL) of a Zarr store geocoder wrote.
    path : str or PathLike
        The COG to write (a local path).
    variable : str, optional
        Variable of a Dataset or store; required when it has more than one image variable.
    client : distributed.Client, optional
        Where the tiles are computed; default the current client, else ``scheduler``.
    scheduler : str, optional
        Scheduler address or ``cluster.json`` when there is no client
        (:func:`geocoder.runtime.dask_client`: default ``DASK_SCHEDULER_ADDRESS``, else a
        local cluster started after the inputs were checked).
    blocksize : int
        Tile side in pixels (a multiple of 16, as TIFF requires).
    overviews : int, optional
        Number of overview levels, each half the size of the previous one (rounded up);
        default: halve until the smallest level fits one block.
    resampling : {"average", "nearest"}, optional
        How overviews are made; default ``"average"`` (exact mean of the valid pixels) for
        floating-point data and ``"nearest"`` for integers (status codes, classes).
    compression : {"deflate", "none"}
        Tile compression.
    predictor : {1, 2, 3}, optional
        TIFF predictor: 1 none, 2 horizontal differencing (integers), 3 floating point;
        default 3 for floats and 2 for integers when compressed, else 1.
    nodata : float, optional
        Nodata value written to the ``GDAL_NODATA`` tag. Default: the source's nodata
        (``.rio.nodata``), else NaN for floating-point data and none for integers. For float
        data NaN pixels are written as ``nodata``.
    bigtiff : bool, optional
        Force BigTIFF (True) or classic TIFF (False); default BigTIFF only when needed.
    overwrite : bool
        Replace an existing ``path`` if geocoder wrote it (never anything else).

    Returns
    -------
    pathlib.Path
        The COG written.

    Raises
    ------
    InputError
        For a missing store or variable, or a refused output (:func:`geocoder.outputs.check_output`).
    ValueError
        For options that do not fit the data.

    Warns
    -----
    GeocoderWarning
        When the source has no CRS: the COG is written without GeoTIFF tags.
    """
    from .runtime import current_client, dask_client

    if blocksize < 16 or blocksize % 16:
        raise ValueError(f"blocksize must be a positive multiple of 16, not {blocksize}")
    if compression not in _COMPRESSION:
        raise ValueError(f"compression must be one of {sorted(_COMPRESSION)}, not {compression!r}")
    if storage.is_url(os.fspath(path)):
        raise ValueError(f"{path}: a COG is written to a local path; copy it to object storage afterwards")
    array, store = _open_source(source, variable)
    final = check_output(path, inputs=(store,) if store else (), overwrite=overwrite, option="--cog")

    crs = array.rio.crs
    transform = array.rio.transform() if crs is not None else None
    if crs is None:
        warnings.warn(f"{store or 'source'}: has no CRS; the COG is written without georeference",
                      GeocoderWarning, stacklevel=2)
    data = array.data if array.ndim == 3 else array.data[None]
    if not isinstance(data, da.Array):
        data = da.from_array(np.asarray(data), chunks=(-1, blocksize, blocksize))
    dtype = _tiff_dtype(np.dtype(data.dtype))
    is_float = np.issubdtype(dtype, np.floating)
    if nodata is None:
        nodata = array.rio.nodata if array.rio.nodata is not None else (math.nan if is_float else None)
    if nodata is not None:
        nodata = float(nodata)
        if not is_float and not (nodata == nodata // 1 and np.iinfo(dtype).min <= nodata <= np.iinfo(dtype).max):
            raise ValueError(f"nodata {nodata} does not fit {dtype} pixels")
    resampling = resampling or ("average" if is_float else "nearest")
    if resampling not in ("average", "nearest"):
        raise ValueError(f"resampling must be 'average' or 'nearest', not {resampling!r}")
    if predictor is None:
        predictor = 1 if compression == "none" else (3 if is_float else 2)
    if predictor not in (1, 2, 3) or (predictor == 3 and not is_float) or (predictor == 2 and is_float):
        raise ValueError(f"predictor {predictor} does not fit {dtype} pixels (3 is for floats, 2 for integers)")

    bands, height, width = data.shape
    n_levels = _levels(width, height, blocksize, overviews)
    fill = nodata if nodata is not None else 0.0
    tasks, layout = _tile_tasks(data.rechunk((-1, blocksize, blocksize)), n_levels, blocksize, _TileSpec(
        blocksize, dtype.str, fill, nodata, compression, predictor, 0, resampling == "average"))

    entries_main = _main_tags(array, store, variable, crs, transform, nodata, dtype, resampling)
    client = client or current_client()
    tmp = storage.temporary_sibling(final)
    spill = storage.temporary_sibling(final) + ".tiles"
    try:
        with dask_client(client, scheduler=scheduler) as c:
            where = _compute_tiles(c, tasks, spill)
        _assemble(tmp, spill, where, layout, blocksize=blocksize, bands=bands, dtype=dtype, spec_compression=compression,
                  predictor=predictor, nodata=nodata, main_tags=entries_main, bigtiff=bigtiff)
        commit_output(tmp, final, overwrite=overwrite)
    except BaseException as exc:
        storage.remove(tmp)
        failure = as_environment_failure(exc, final)
        if failure is not None:
            raise failure from exc
        raise
    finally:
        storage.remove(spill)
    return Path(final)


def _tile_tasks(data: da.Array, n_levels: int, blocksize: int, spec: _TileSpec):
    """One delayed ``bytes`` per tile of every level, and the levels' ``(height, width, ny, nx)``."""
    tasks: dict[tuple[int, int, int], object] = {}
    layout: list[tuple[int, int, int, int]] = []
    level = data
    if spec.average and n_levels:
        level = da.map_blocks(_accumulate, data, nodata=spec.nodata, new_axis=0, chunks=((2,), *data.chunks),
                              dtype=np.float64)
    for k in range(n_levels + 1):
        if k:
            level = _next_level(level, blocksize, spec.average)
        height, width = level.shape[-2:]
        # unoptimised: the levels share the source blocks, optimised once when computed together
        blocks = (data if k == 0 else level).to_delayed(optimize_graph=False)
        blocks = blocks.reshape(blocks.shape[-2:])
        layout.append((height, width, *blocks.shape))
        s = _TileSpec(**{**spec.__dict__, "level": k})
        for (iy, ix), block in np.ndenumerate(blocks):
            tasks[(k, iy, ix)] = dask.delayed(_encode, pure=True)(block, s)
    return tasks, layout


def _next_level(level: da.Array, blocksize: int, average: bool) -> da.Array:
    """The level below halved: 2 x 2 sums of ``(sum, count)``, or every other pixel."""
    if not average:
        return level[..., ::2, ::2].rechunk({level.ndim - 2: blocksize, level.ndim - 1: blocksize})
    h, w = level.shape[-2:]
    if h % 2 or w % 2:
        level = da.pad(level, ((0, 0), (0, 0), (0, h % 2), (0, w % 2)))
    level = level.rechunk((2, -1, 2 * blocksize, 2 * blocksize))
    chunks = (*level.chunks[:2], tuple(c // 2 for c in level.chunks[2]), tuple(c // 2 for c in level.chunks[3]))
    return level.map_blocks(_halve, chunks=chunks, dtype=np.float64)


def _compute_tiles(client, tasks: dict, spill: str) -> dict[tuple[int, int, int], tuple[int, int]]:
    """Compute every tile on the cluster; append each to ``spill`` as it arrives.

    Returns where each tile is in the spill file: ``(offset, size)``.
    """
    from distributed import as_completed

    bar = progress.current()
    bar.phase("COG tiles", len(tasks))
    keys = list(tasks)
    futures = client.compute([tasks[k] for k in keys])
    key_of = {f.key: k for f, k in zip(futures, keys)}
    where: dict[tuple[int, int, int], tuple[int, int]] = {}
    offset = 0
    try:
        with open(spill, "wb") as f:
            for fut, data in as_completed(futures, with_results=True):
                f.write(data)
                where[key_of[fut.key]] = (offset, len(data))
                offset += len(data)
                fut.release()
                bar.advance()
    finally:
        for fut in futures:
            fut.cancel()
        bar.close()
    return where


def _main_tags(array, store, variable, crs, transform, nodata, dtype, resampling) -> list[_Entry]:
    """Tags only the full-resolution IFD carries: georeference and GDAL metadata."""
    items = {**product_attrs(PRODUCT), "variable": str(variable or array.name or ""), "source": str(store or ""),
             "overview_resampling": resampling}
    entries = [_entry(42112, _ASCII, _metadata_xml(items))]
    if crs is not None:
        entries += _geotags(crs, transform)
    return entries


def _assemble(tmp, spill, where, layout, *, blocksize, bands, dtype, spec_compression, predictor, nodata, main_tags, bigtiff) -> None:
    """Write the COG: header, ghost area, IFDs (full resolution first), tiles (smallest level first)."""
    sizes = {k: n for k, (_, n) in where.items()}
    order = [(k, iy, ix) for k in range(len(layout) - 1, -1, -1) for iy in range(layout[k][2]) for ix in range(layout[k][3])]
    data_bytes = sum(sizes[t] + 8 for t in order)
    dtype = np.dtype(dtype)
    sample_format = 3 if dtype.kind == "f" else (2 if dtype.kind == "i" else 1)

    def ifds(big: bool, offsets: dict) -> bytes:
        start = (16 if big else 8) + len(_ghost())
        out = bytearray()
        for k, (h, w, ny, nx) in enumerate(layout):
            tiles = [(k, iy, ix) for iy in range(ny) for ix in range(nx)]
            entries = [
                _entry(254, _LONG, 0 if k == 0 else 1),
                _entry(256, _LONG, w), _entry(257, _LONG, h),
                _entry(258, _SHORT, [8 * dtype.itemsize] * bands),
                _entry(259, _SHORT, _COMPRESSION[spec_compression]),
                _entry(262, _SHORT, 1),
                _entry(277, _SHORT, bands),
                _entry(284, _SHORT, 1),
                _entry(322, _LONG, blocksize), _entry(323, _LONG, blocksize),
                _entry(324, _LONG8 if big else _LONG, [offsets.get(t, 0) for t in tiles]),
                _entry(325, _LONG8 if big else _LONG, [sizes[t] for t in tiles]),
                _entry(339, _SHORT, [sample_format] * bands),
            ]
            if predictor != 1:
                entries.append(_entry(317, _SHORT, predictor))
            if bands > 1:
                entries.append(_entry(338, _SHORT, [0] * (bands - 1)))  # extra samples: unspecified
            if nodata is not None:
                entries.append(_entry(42113, _ASCII, _nodata_text(nodata, dtype)))
            if k == 0:
                entries += main_tags
            size = len(_ifd(entries, start + len(out), 0, big))
            next_ifd = 0 if k == len(layout) - 1 else start + len(out) + size
            out += _ifd(entries, start + len(out), next_ifd, big)
        return bytes(out)

    big = bigtiff
    if big is None:
        big = (16 + len(_ghost()) + len(ifds(True, {})) + data_bytes) >= 2**32
    head_len = (16 if big else 8) + len(_ghost()) + len(ifds(big, {}))
    if not big and head_len + data_bytes >= 2**32:
        raise ValueError("the COG needs BigTIFF (more than 4 GiB); do not pass bigtiff=False")
    offsets, pos = {}, head_len
    for t in order:
        offsets[t] = pos + 4  # after the 4-byte size leader
        pos += sizes[t] + 8
    header = (b"II" + struct.pack("<HHHQ", 43, 8, 0, 16 + len(_ghost())) if big
              else b"II" + struct.pack("<HI", 42, 8 + len(_ghost())))
    with open(spill, "rb") as src, open(tmp, "wb") as f:
        f.write(header + _ghost() + ifds(big, offsets))
        for t in order:
            at, n = where[t]
            tile = os.pread(src.fileno(), n, at)
            f.write(struct.pack("<I", n) + tile + tile[-4:])
        f.flush()
        os.fsync(f.fileno())


