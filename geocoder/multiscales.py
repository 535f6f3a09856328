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
    one below it as computed, with the number of valid full-resolution pixels behind each
    pixel (kept in memory between the levels, never stored):
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
* the work runs on the Dask scheduler of the writer (``client``): one task per output chunk
  and variable, which reads (level 1: the root's 2 x 2 chunks) or takes from the tasks below
  it (the level below as computed) the block it covers, reduces it and writes its chunk, so a
  worker holds a few chunks, never a scene (an 8192^2 output of seven variables, tile 1024,
  2 workers: 147 tasks, 4.3-6.3 s, against 1,011 tasks of reads, rechunks, casts and writes
  and 8.6-11.5 s with an xarray graph per level). Only variables on the ``(y, x)`` grid of
  the root are levelled (not tie-point tables, sub-groups or other grids).

Writers call it on their temporary store before :func:`geocoder.outputs.commit_output`, so
a committed store always has all its levels; the ``multiscales`` attribute is written last.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import dask
import dask.array as da
import numba
import numpy as np
import xarray as xr
from affine import Affine
from dask.delayed import Delayed

from . import progress, storage
from .conventions import GRID_MAPPING, _declare, _on_grid, georeference, pixel_centres

__all__ = ["MULTISCALES_CONVENTION", "OverviewPlan", "level_shapes", "plan_overviews", "write_overviews"]

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


@dataclass(frozen=True)
class _Spec:
    """What the tasks of one variable need (pickled to the workers with them)."""

    store: str
    name: str
    source: xr.Variable  # the root's variable, lazily read and decoded (as xarray.open_dataset opens it)
    encoding: dict  # how the levels store it (its dtype, fill value; :func:`_encoding`)
    averaged: bool  # the mean of the valid pixels (else the top-left pixel)
    chunk: tuple[int, int]  # (rows, cols) of a chunk, the same at every level
    shapes: tuple[tuple[int, int], ...]  # (rows, cols) of the root, then of every level
    written: str  # when the root's variable was written (:func:`geocoder.storage.identity`), for the task keys

    def __dask_tokenize__(self) -> tuple:
        return (self.store, self.name, self.averaged, self.chunk, self.shapes, self.written)


def _level_chunk(spec: _Spec, k: int, iy: int, ix: int, *below: tuple | None) -> tuple | None:
    """Chunk ``(iy, ix)`` of level ``k`` of one variable, written into the store.

    Computed from the 2 x 2 chunks of level ``k - 1`` it covers: for ``k = 1`` the root (its
    block of ``spec.source``); else ``below``, the returns of those chunks' own tasks in
    row-major order (None past the level's edge), so no level is read back and the
    valid-pixel counts of the means never leave memory. Returns, for the next level, the
    chunk's values as stored and the counts of its means (None at the last level).
    """
    cy, cx = spec.chunk
    if k == 1:
        h, w = spec.shapes[0]
        values = spec.source[..., 2 * iy * cy : min(2 * (iy + 1) * cy, h), 2 * ix * cx : min(2 * (ix + 1) * cx, w)].values
        counts = None
    else:
        def joined(part: int) -> np.ndarray:
            rows = [[b[part] for b in pair if b is not None] for pair in (below[:2], below[2:])]
            return np.concatenate([np.concatenate(r, axis=-1) for r in rows if r], axis=-2)
        values, counts = joined(0), joined(1) if spec.averaged else None
    if spec.averaged:
        mean, n = _halve_mean(values, counts)
        out = (mean.astype(values.dtype), n.astype(np.min_scalar_type(4**k)))
    else:
        out = (values[..., ::2, ::2], None)
    h, w = out[0].shape[-2:]
    stored = xr.conventions.encode_cf_variable(xr.Variable(spec.source.dims, out[0], encoding=dict(spec.encoding)))
    storage.open_array(spec.store, f"{k}/{spec.name}", mode="r+")[..., iy * cy : iy * cy + h, ix * cx : ix * cx + w] = stored.values
    return out if k < len(spec.shapes) - 1 else None


def _level_tasks(spec: _Spec) -> dict[tuple[int, int, int], Delayed]:
    """One task per output chunk of every level of one variable (:func:`_level_chunk`), keyed
    ``(k, iy, ix)``; a level's tasks take the returns of the ones below them."""
    cy, cx = spec.chunk
    token = dask.base.tokenize(spec)
    tasks: dict[tuple[int, int, int], Delayed] = {}
    for k in range(1, len(spec.shapes)):
        h, w = spec.shapes[k]
        for iy in range(-(-h // cy)):
            for ix in range(-(-w // cx)):
                below = [tasks.get((k - 1, 2 * iy + a, 2 * ix + b)) for a in (0, 1) for b in (0, 1)] if k > 1 else []
                tasks[(k, iy, ix)] = dask.delayed(_level_chunk, pure=True)(
                    spec, k, iy, ix, *below, dask_key_name=f"overview-{spec.name}-{k}-{iy}-{ix}-{token}")
    return tasks


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

    def specs(self, shapes: list[tuple[int, int]]) -> list[_Spec]:
        """The tasks' :class:`_Spec` of every variable, for levels of ``shapes``."""
        source = xr.open_dataset(self.store, engine="zarr", consolidated=False, chunks=None)
        return [_Spec(store=self.store, name=n, source=source[n].variable,
                      encoding=_encoding(self.root[n], self.chunks[n], self.root[n].shape),
                      averaged=self.methods[n] == "average", chunk=tuple(self.chunks[n][-2:]),
                      shapes=((self.root.sizes["y"], self.root.sizes["x"]), *shapes),
                      written=repr(sorted(storage.identity(storage.join(self.store, n)).items()))) for n in self.names]

    def template(self, k: int, shape: tuple[int, int]) -> xr.Dataset:
        """Level ``k`` (of ``shape``) as an empty dataset: what its store holds but the values
        (dtypes, chunks, encoding, attributes, coordinates); ``to_zarr(compute=False)`` of it
        writes the level's metadata and coordinates, :func:`_level_chunk` the values."""
        variables = {}
        for name in self.names:
            src = self.root[name]
            data = da.empty((*src.shape[:-2], *shape), dtype=src.dtype,
                            chunks=tuple(min(c, n) for c, n in zip(self.chunks[name], (*src.shape[:-2], *shape))))
            cell = "y: x: mean" if self.methods[name] == "average" else "y: x: point"
            attrs = {a: v for a, v in src.attrs.items() if a != "_CRS"}
            attrs["cell_methods"] = f"{attrs['cell_methods']} {cell}" if attrs.get("cell_methods") else cell
            var = xr.DataArray(data, dims=src.dims, attrs=attrs)
            var.encoding = _encoding(src, self.chunks[name], data.shape)
            variables[name] = var
        level = xr.Dataset(variables, coords=self._coords(variables), attrs={"overview_factor": 2**k})
        transform = self.transform * Affine.scale(2**k)
        if self.crs is not None:
            return georeference(level, self.crs, transform)
        x, y = pixel_centres(transform, shape)
        return level.assign_coords(x=("x", x, dict(self.root["x"].attrs) if "x" in self.root.coords else {}),
                                   y=("y", y, dict(self.root["y"].attrs) if "y" in self.root.coords else {}))

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
    module documentation for the layout and the conventions. The same as
    ``plan_overviews(store, variables=..., min_size=...).compute(client)``.

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
        Where the levels are computed (one task per output chunk and variable); default the current Dask
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
    return plan_overviews(store, variables=variables, min_size=min_size).compute(client)


@dataclass
class OverviewPlan:
    """The overview levels of a store, their metadata written, their values still to compute
    (:func:`plan_overviews`)."""

    store: str
    levels: _Levels | None  # None: nothing to level
    shapes: list[tuple[int, int]]

    def compute(self, client=None) -> list[int]:
        """Compute and write the levels' values, then the root's ``multiscales`` attribute
        (last: a store with the attribute has all its levels).

        Returns the levels written (as :func:`write_overviews`).
        """
        import zarr

        if self.levels is None or not self.shapes:
            return []
        levels, shapes, store = self.levels, self.shapes, self.store
        cy, cx = levels.chunks[levels.names[0]][-2:]
        tiles = sum(-(-h // cy) * -(-w // cx) for h, w in shapes)  # the progress counts each level's output chunks
        # one task per output chunk and variable; the last level's depend on every other
        last = [t for spec in levels.specs(shapes) for (k, _, _), t in _level_tasks(spec).items() if k == len(shapes)]
        bar = progress.current()
        bar.phase("overview levels", tiles)
        try:
            dask.compute(*last, **({"scheduler": client} if client is not None else {}))
            bar.advance(tiles)
        finally:
            bar.close()
            storage.remove(storage.join(store, COUNTS_GROUP))  # left by an earlier version

        group = zarr.open_group(store, mode="r+", zarr_format=3)
        attrs = group.attrs.asdict()
        _declare(attrs, MULTISCALES_CONVENTION)
        group.attrs.update({"zarr_conventions": attrs["zarr_conventions"], "multiscales": levels.layout(shapes)})
        return list(range(1, len(shapes) + 1))


def plan_overviews(
    store: str | os.PathLike,
    *,
    variables: list[str] | tuple[str, ...] | None = None,
    min_size: int | None = None,
) -> OverviewPlan:
    """The first half of :func:`write_overviews` (same parameters and errors): the levels'
    groups, metadata and coordinates written, nothing computed.

    It needs the root's metadata only, not its values, so a writer may call it while the
    root's chunks are still being written (``register`` does, from a thread, while its
    output tiles compute) and call :meth:`OverviewPlan.compute` once they are all written.
    """
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
        return OverviewPlan(store, None, [])
    levels = _Levels(store, names, root)
    if min_size is None:
        min_size = max(max(levels.chunks[n][-2:]) for n in names)
    shapes = level_shapes((root.sizes["y"], root.sizes["x"]), min_size)
    for k, shape in enumerate(shapes, start=1):  # metadata and coordinates; the values in compute()
        levels.template(k, shape).to_zarr(store, group=str(k), mode="w", zarr_format=3, consolidated=False, compute=False)
    return OverviewPlan(store, levels, shapes)
