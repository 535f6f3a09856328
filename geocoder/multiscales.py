"""Overview levels inside the Zarr stores geocoder writes (the ``multiscales`` convention).

:func:`write_overviews` adds reduced-resolution copies of a finished store's image variables,
for quick looks, without changing the full-resolution data:

* the root group stays level 0, exactly as written (its readers see no difference but the
  new ``multiscales`` root attribute and one more entry in ``zarr_conventions``); level ``k`` is the child group ``"k"`` (``"1"``, ``"2"``, ...), each side
  halved (rounded up) from level ``k - 1``, down to the first level whose larger side is at
  most ``min_size`` (default: one chunk of the root, as :func:`geocoder.cog.to_cog` stops its
  overviews at one block);
* the root attribute ``multiscales`` lists the levels (zarr-conventions/multiscales v1):
  ``{"asset": ".", ...}`` for the root itself, then ``{"asset": "k", "derived_from": "k-1",
  "transform": {"scale": [2.0, 2.0], "translation": [0.0, 0.0]}, "spatial:shape": ...,
  "spatial:transform": ...}``; the convention is declared in the root's ``zarr_conventions``
  list next to ``proj:`` and ``spatial:``;
* every level is georeferenced like the root (:func:`geocoder.conventions.georeference`
  with the root's transform times ``Affine.scale(2**k)``), so
  ``xr.open_zarr(store, group="1", decode_coords="all").rio.transform()`` is the level's;
  a root without CRS (pixel coordinates) gets level ``x``/``y`` in the root's pixel units
  (centres of the covered full-resolution pixels);
* the values follow :func:`geocoder.cog.to_cog`'s overviews, so a level and the COG overview
  of the same factor are equal:

  - floating-point variables: the exact mean of the valid (non-NaN, after decoding the
    fill value) full-resolution pixels a level pixel covers. A level is computed from the
    one below it, so each level also keeps the number of valid full-resolution pixels
    behind each pixel (in a scratch group of the store, removed when the levels are done):
    ``mean_k = sum(mean_{k-1} * n_{k-1}) / sum(n_{k-1})`` over 2 x 2 pixels;
  - integer and boolean variables (``status`` flags, a mosaic's ``source`` index): the
    nearest pixel, the top-left one of the covered block (full-resolution pixel
    ``(i * 2**k, j * 2**k)``). An average of flag codes is no flag, and a most-common
    value is neither exact across levels (the mode of modes is not the mode of the block)
    nor unique for a 2 x 2 block (often tied); the nearest value is a value of the data,
    exact at every level, GDAL's default for overviews and what the COG export uses;

* dtype, fill value, compressors, the variables' attributes (CF ``long_name``, ``units``,
  ``flag_values``, ...) and the root's chunk shape are kept; ``cell_methods`` says how the
  level was made (``"y: x: mean"`` or ``"y: x: point"``);
* the work runs on the Dask scheduler of the writer (``client``): one task per output chunk,
  reading the 2 x 2 chunks of the level below it, so a worker holds a few chunks, never a
  scene. Only variables on the ``(y, x)`` grid of the root are levelled (not tie-point
  tables, sub-groups or other grids).

Writers call it on their temporary store before :func:`geocoder.outputs.commit_output`, so
a committed store always has all its levels; the ``multiscales`` attribute is written last.
"""

from __future__ import annotations

import os

import dask
import dask.array as da
import numba
import numpy as np
import xarray as xr
from affine import Affine

from . import progress, storage
from .conventions import GRID_MAPPING, _declare, _on_grid, georeference, pixel_centres

__all__ = ["MULTISCALES_CONVENTION", "level_shapes", "write_overviews"]

#: Declaration of the ``multiscales`` Zarr convention (zarr-conventions/multiscales, v1).
MULTISCALES_CONVENTION = {
    "schema_url": "https://raw.githubusercontent.com/zarr-conventions/multiscales/refs/tags/v1/schema.json",
    "spec_url": "https://github.com/zarr-conventions/multiscales/blob/v1/README.md",
    "uuid": "d35379db-88df-4056-af3a-620245f8e347",
    "name": "multiscales",
    "description": "Multiscale layout of zarr datasets",
}

#: Scratch group where earlier versions kept the valid-pixel counts between levels (removed if found).
COUNTS_GROUP = "_overview_counts"

#: Encoding kept from the root's variables (chunks are the root's, cut to the level's shape; no shards:
#: the levels are small and a cut chunk would not divide the root's shard).
_ENCODING_KEYS = ("compressors", "filters", "serializer", "dtype", "_FillValue", "fill_value")


# ---------------------------------------------------------------------------- worker side


@numba.njit(nogil=True, cache=True)
def _cell(v, n, k, r, c, weighted):  # pragma: no cover - compiled
    """``(v * n, n)`` of one pixel; ``(0, 0)`` outside the array or where ``v`` is NaN."""
    if r >= v.shape[1] or c >= v.shape[2]:
        return 0.0, 0.0
    x = np.float64(v[k, r, c])
    if x != x:
        return 0.0, 0.0
    m = np.float64(n[k, r, c]) if weighted else 1.0
    return x * m, m


@numba.njit(nogil=True, cache=True)
def _halve_kernel(v, n, out):  # pragma: no cover - compiled
    """2 x 2 block means of the valid (non-NaN) ``v`` weighted by ``n`` (empty ``n``: 1 each),
    summed ``(top-left + bottom-left) + (top-right + bottom-right)``, and the counts, into ``out``."""
    weighted = n.shape[0] > 0
    for k in range(v.shape[0]):
        for i in range(out.shape[2]):
            r = 2 * i
            for j in range(out.shape[3]):
                c = 2 * j
                t00, n00 = _cell(v, n, k, r, c, weighted)
                t10, n10 = _cell(v, n, k, r + 1, c, weighted)
                t01, n01 = _cell(v, n, k, r, c + 1, weighted)
                t11, n11 = _cell(v, n, k, r + 1, c + 1, weighted)
                total = (t00 + t10) + (t01 + t11)
                count = (n00 + n10) + (n01 + n11)
                out[0, k, i, j] = total / count if count > 0 else np.nan
                out[1, k, i, j] = count


def _halve_mean(values: np.ndarray, counts: np.ndarray | None = None) -> np.ndarray:
    """Mean of the valid pixels of every 2 x 2 block, and how many full-resolution pixels it rests on.

    ``values`` are the means of the level below (``counts`` full-resolution pixels each; the
    full resolution itself when ``counts`` is None). Odd sides are padded with empty pixels.
    Returns ``(2, ..., ceil(h / 2), ceil(w / 2))`` float64: the means (NaN where nothing is
    valid) and the counts.
    """
    v = np.asarray(values)
    lead, (h, w) = v.shape[:-2], v.shape[-2:]
    v3 = v.reshape(-1, h, w)
    n3 = np.empty((0, 0, 0), dtype=np.float64) if counts is None else np.asarray(counts).reshape(-1, h, w)
    out = np.empty((2, v3.shape[0], (h + 1) // 2, (w + 1) // 2))
    _halve_kernel(v3, n3, out)
    return out.reshape(2, *lead, *out.shape[2:])


# ---------------------------------------------------------------------------- graphs


def _halved(chunks: tuple[int, ...]) -> tuple[int, ...]:
    return tuple((c + 1) // 2 for c in chunks)


def _mean_level(values: da.Array, counts: da.Array | None, dtype: np.dtype, count_dtype: np.dtype) -> tuple[da.Array, da.Array]:
    """The next level of an averaged variable and its counts (one task per output chunk)."""
    args = (values,) if counts is None else (values, counts)
    chunks = ((2,), *values.chunks[:-2], _halved(values.chunks[-2]), _halved(values.chunks[-1]))
    pair = da.map_blocks(_halve_mean, *args, new_axis=0, chunks=chunks, dtype=np.float64)
    return pair[0].astype(dtype), pair[1].astype(count_dtype)


def _nearest_level(values: da.Array) -> da.Array:
    """The next level of a categorical variable: the top-left pixel of every 2 x 2 block."""
    return values[..., ::2, ::2]


def level_shapes(shape: tuple[int, int], min_size: int) -> list[tuple[int, int]]:
    """Shapes ``(rows, cols)`` of the overview levels 1, 2, ... of a ``shape`` grid.

    Each level halves the one before (rounded up) until the larger side is at most ``min_size``.

    Parameters
    ----------
    shape : tuple of int
        ``(rows, cols)`` of the full resolution.
    min_size : int
        Largest side of the last level (at least 1).

    Returns
    -------
    list of tuple of int
        One shape per level; empty when ``shape`` already fits ``min_size``.
    """
    if min_size < 1:
        raise ValueError(f"min_size must be at least 1, not {min_size}")
    h, w = shape
    out = []
    while max(h, w) > min_size:
        h, w = (h + 1) // 2, (w + 1) // 2
        out.append((h, w))
    return out


def _pixel_transform(root: xr.Dataset) -> Affine:
    """The affine of the root's ``x``/``y`` coordinates (pixel centres, regularly spaced), corners."""
    def step(name: str) -> tuple[float, float]:
        if name not in root.coords:
            return 0.0, 1.0
        values = np.asarray(root[name].values, dtype=np.float64)
        spacing = float(values[1] - values[0]) if values.size > 1 else 1.0
        return float(values[0]), spacing

    x0, dx = step("x")
    y0, dy = step("y")
    return Affine(dx, 0.0, x0 - dx / 2, 0.0, dy, y0 - dy / 2)


def _method(var: xr.DataArray) -> str:
    """``"average"`` for floating-point data as stored, ``"nearest"`` for integers and booleans."""
    stored = np.dtype(var.encoding.get("dtype", var.dtype))
    return "average" if stored.kind == "f" else "nearest"


def _encoding(var: xr.DataArray, chunks: tuple[int, ...], shape: tuple[int, ...]) -> dict:
    enc = {k: var.encoding[k] for k in _ENCODING_KEYS if var.encoding.get(k) is not None}
    enc["chunks"] = tuple(min(c, n) for c, n in zip(chunks, shape))
    return enc


class _Levels:
    """The state of one :func:`write_overviews` call: what the root looks like, what each level holds."""

    def __init__(self, store: str, names: list[str], root: xr.Dataset) -> None:
        self.store = store
        self.names = names
        self.root = root
        self.methods = {n: _method(root[n]) for n in names}
        self.chunks = {n: tuple(root[n].encoding.get("chunks") or root[n].data.chunksize) for n in names}
        self.crs = root.rio.crs if GRID_MAPPING in root.coords else None
        self.transform = root.rio.transform() if self.crs is not None else _pixel_transform(root)
        self._opened: dict[tuple, xr.Dataset] = {}

    def _open(self, group: str | None, name: str) -> xr.DataArray:
        """One variable of a level (``group``), in dask chunks of 2 x 2 of its stored chunks."""
        cy, cx = self.chunks[name][-2:]
        key = (group, cy, cx)
        if key not in self._opened:
            # every chunk's task holds the array's reader itself (inline_array): as one shared input
            # it lived on one worker and drew the level's tasks there (5 of 7 at 2048², two workers)
            self._opened[key] = xr.open_dataset(self.store, engine="zarr", group=group, consolidated=False,
                                                chunks={"y": 2 * cy, "x": 2 * cx}, inline_array=True)
        return self._opened[key][name]

    def dataset(self, k: int, below: dict[str, xr.DataArray] | None = None,
                below_counts: dict[str, da.Array] | None = None) -> tuple[xr.Dataset, dict[str, da.Array]]:
        """Level ``k`` (lazy) from level ``k - 1``, and the valid-pixel counts of its averages.

        ``below`` and ``below_counts`` are level ``k - 1`` as this method returned it; None for
        ``k = 1`` (the root, as stored).
        """
        count_dtype = np.min_scalar_type(4**k)
        variables, counts = {}, {}
        for name in self.names:
            if below is None:
                values, n = self._open(None, name), None
            else:  # the level below, its chunks merged 2 x 2: one task per output chunk
                cy, cx = self.chunks[name][-2:]
                values = below[name].chunk({"y": 2 * cy, "x": 2 * cx})
                n = below_counts.get(name)
                n = None if n is None else n.rechunk(values.data.chunks)
            if self.methods[name] == "average":
                data, counts[name] = _mean_level(values.data, n, values.dtype, count_dtype)
                cell = "y: x: mean"
            else:
                data = _nearest_level(values.data)
                cell = "y: x: point"
            attrs = {a: v for a, v in self.root[name].attrs.items() if a != "_CRS"}
            attrs["cell_methods"] = f"{attrs['cell_methods']} {cell}" if attrs.get("cell_methods") else cell
            var = xr.DataArray(data, dims=self.root[name].dims, attrs=attrs)
            var.encoding = _encoding(self.root[name], self.chunks[name], data.shape)
            variables[name] = var
        level = xr.Dataset(variables, coords=self._coords(variables), attrs={"overview_factor": 2**k})
        transform = self.transform * Affine.scale(2**k)
        if self.crs is not None:
            level = georeference(level, self.crs, transform)
        else:
            shape = (level.sizes["y"], level.sizes["x"])
            x, y = pixel_centres(transform, shape)
            level = level.assign_coords(x=("x", x, dict(self.root["x"].attrs) if "x" in self.root.coords else {}),
                                        y=("y", y, dict(self.root["y"].attrs) if "y" in self.root.coords else {}))
        return level, counts

    def _coords(self, variables: dict[str, xr.DataArray]) -> dict:
        """The root's coordinates off the (y, x) grid that the level's variables use (``band``, ...)."""
        dims = {d for v in variables.values() for d in v.dims}
        out = {}
        for name, coord in self.root.coords.items():
            if name in ("x", "y", GRID_MAPPING) or {"x", "y"} & set(coord.dims) or not set(coord.dims) <= dims:
                continue
            out[name] = coord.variable.copy(deep=False)
        return out

    def layout(self, shapes: list[tuple[int, int]]) -> dict:
        """The ``multiscales`` attribute of the root for levels of ``shapes``."""
        def entry(k: int, shape: tuple[int, int]) -> dict:
            item: dict = {"asset": "." if k == 0 else str(k)}
            if k:
                item["derived_from"] = "." if k == 1 else str(k - 1)
            item["transform"] = {"scale": [2.0, 2.0] if k else [1.0, 1.0], "translation": [0.0, 0.0]}
            if self.crs is not None:
                t = self.transform * Affine.scale(2**k)
                item["spatial:shape"] = [int(shape[0]), int(shape[1])]
                item["spatial:transform"] = [t.a, t.b, t.c, t.d, t.e, t.f]
            return item

        root_shape = (self.root.sizes["y"], self.root.sizes["x"])
        methods = set(self.methods.values())
        return {
            "layout": [entry(k, s) for k, s in enumerate([root_shape, *shapes])],
            "resampling_method": "average" if "average" in methods else "nearest",
            # geocoder's addition (additional properties are allowed): the method of every variable
            "resampling_method_by_variable": dict(self.methods),
        }


def write_overviews(
    store: str | os.PathLike,
    *,
    variables: list[str] | tuple[str, ...] | None = None,
    min_size: int | None = None,
    client=None,
) -> list[int]:
    """Write overview levels of a finished Zarr store into the store itself (``multiscales``).

    Level ``k`` (child group ``str(k)``) halves level ``k - 1`` on each side (rounded up),
    starting from the root (level 0, not changed); floating-point variables take the mean of
    the valid full-resolution pixels, integer ones the nearest (top-left) pixel. See the
    module documentation for the layout and the conventions.

    Parameters
    ----------
    store : str or PathLike
        The store (local path or fsspec URL), complete at full resolution; the levels and the
        ``multiscales`` root attribute are added (levels already there are replaced).
    variables : sequence of str, optional
        Root variables to level; default every data variable on the root's ``(y, x)`` grid.
    min_size : int, optional
        Levels are made until the larger side of the last one is at most ``min_size``;
        default the larger side of a chunk of the root (the last level is one chunk).
    client : distributed.Client, optional
        Where the levels are computed (one task per output chunk); default the current Dask
        scheduler.

    Returns
    -------
    list of int
        The levels written (``[1, 2, ...]``, group names ``"1"``, ``"2"``, ...); empty when
        the root already fits ``min_size`` or has no variable on the grid (then nothing is
        written).

    Raises
    ------
    ValueError
        If ``store`` is not a Zarr store, a requested variable is not on the ``(y, x)``
        grid, or ``min_size`` is below 1.
    """
    import zarr

    store = storage.normalize(store)
    if not storage.is_store(store):
        raise ValueError(f"{store}: is not a Zarr store")
    root = xr.open_zarr(store, consolidated=False, decode_coords="all")
    grid = [n for n, v in root.data_vars.items() if _on_grid(v)]
    if variables is None:
        names = sorted(grid)
    else:
        names = list(variables)
        off = [n for n in names if n not in grid]
        if off:
            raise ValueError(f"{store}: not variables on the (y, x) grid: {', '.join(off)}; those are: {', '.join(sorted(grid))}")
    if not names:
        return []
    levels = _Levels(store, names, root)
    if min_size is None:
        min_size = max(max(levels.chunks[n][-2:]) for n in names)
    shapes = level_shapes((root.sizes["y"], root.sizes["x"]), min_size)
    if not shapes:
        return []

    cy, cx = levels.chunks[names[0]][-2:]
    tiles = [-(-h // cy) * -(-w // cx) for h, w in shapes]  # the progress counts each level's output chunks
    bar = progress.current()
    bar.phase("overview levels", sum(tiles))
    # every level in one graph, each from the one below as computed (the same values as stored:
    # float32 means and their valid counts), so no level is read back and no count is stored
    writes, below, below_counts = [], None, None
    for k in range(1, len(shapes) + 1):
        level, below_counts = levels.dataset(k, below, below_counts)
        writes.append(level.to_zarr(store, group=str(k), mode="w", zarr_format=3, consolidated=False, compute=False))
        below = level
    try:
        dask.compute(*writes, **({"scheduler": client} if client is not None else {}))
        bar.advance(sum(tiles))
    finally:
        bar.close()
        storage.remove(storage.join(store, COUNTS_GROUP))  # left by an earlier version

    group = zarr.open_group(store, mode="r+", zarr_format=3)
    attrs = group.attrs.asdict()
    _declare(attrs, MULTISCALES_CONVENTION)
    group.attrs.update({"zarr_conventions": attrs["zarr_conventions"], "multiscales": levels.layout(shapes)})
    return list(range(1, len(shapes) + 1))
