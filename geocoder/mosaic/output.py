"""The mosaic's output grid and its tiles: scene pixel <-> output pixel mappings, the empty store,
one task per output tile (:func:`mosaic_tile`: every scene's window sampled once, blended across
the seams), the store's attributes, and reading a written mosaic back (models, positions)."""

from __future__ import annotations

import json
import math
import os

import dask.array as da
import numpy as np
import xarray as xr
from affine import Affine

from ..conventions import georeference, status_attrs
from ..errors import InputError
from ..geometry import pixel_to_world, world_to_pixel
from ..outputs import product_attrs
from ..scene import scene_transform
from ..status import Status, positioned
from ..tiles import TileGrid
from .compose import NO_SOURCE, blend, centre_score
from .layers import NODE_STEP, field_layers, model_layers, pixel_sigma, sample_field
from .outgrid import Reprojected, from_map, other_grid, to_map
from .projection import project_window
from .seamplan import read_labels
from .sensors import model_from_dict, model_to_dict
from .summary import MosaicSummary


def scene_to_map(mapping_to_ref, transform: Affine):
    """Scene pixel -> map coordinates, from scene pixel -> reference pixel and the reference's transform."""
    def f(x, y):
        rx, ry = mapping_to_ref(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        return pixel_to_world(transform, rx, ry)

    return f


def shifted(to_ref, origin: tuple[int, int]):
    """Scene pixel -> output pixel, from scene pixel -> reference pixel and the output's origin."""
    def f(x, y):
        rx, ry = to_ref(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        return rx - origin[0], ry - origin[1]

    return f


def through_map(to_ref, transform: Affine, grid: Affine | Reprojected):
    """Scene pixel -> output pixel of any output grid, through the reference's map coordinates."""
    def f(x, y):
        rx, ry = to_ref(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        return from_map(grid, *pixel_to_world(transform, rx, ry))

    return f


def output_crs(ref: xr.DataArray, reference, resolution: float | None, crs) -> str | None:
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


def scene_xy(model, params, transform: Affine | Reprojected, window: tuple[int, int, int, int], located: dict | None,
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


def mosaic_tile(store: str, window: tuple[int, int, int, int], transform: Affine | Reprojected, models: list, readers: list,
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
        sub = _scene_window(ext, boxes[k])  # the scene's part of the tile: outside its box it sees nothing
        if sub[0] == sub[1]:
            continue
        sl = (slice(sub[0] - r0, sub[1] - r0), slice(sub[2] - c0, sub[3] - c0))
        x, y = scene_xy(model, params, transform, sub, fields[k], origin, None if heights is None else heights[sl])
        s = centre_score(x, y, shape)
        if not np.any(s <= 1.0):
            continue
        scores[i][sl] = np.where(s <= 1.0, s, np.nan)
        values[i][(slice(None), *sl)] = (balance[k, :, 0, None, None] * reader.sample(x, y, method=method)
                                         + balance[k, :, 1, None, None])
        codes[i][sl], sx, sy = field_layers(fields[k], sub, origin, transform)
        cov_model, inverse = model_layers(model, params, None if covs is None else covs[k], transform, sub, dem,
                                          None if unmodelled is None else unmodelled[k])
        sigmas[i][(slice(None), *sl)] = pixel_sigma(codes[i][sl], cov_model, inverse, sx, sy)
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


def _scene_window(window: tuple[int, int, int, int], box, step: int = NODE_STEP) -> tuple[int, int, int, int]:
    """The part of ``window`` (``row0, row1, col0, col1``) within a scene's footprint ``box``, its
    start a multiple of ``step`` from the window's and its length one more than a multiple of it
    (or reaching the window's end): the interpolation nodes of :func:`scene_xy` and
    :func:`~geocoder.mosaic.layers.model_layers` are then those of the whole window, so every
    pixel gets the same values as there. Empty (zero rows) where the box misses the window."""
    out = []
    for lo, hi, b0, b1 in ((window[0], window[1], box[0], box[1]), (window[2], window[3], box[2], box[3])):
        a, b = max(int(b0), lo), min(int(b1), hi)
        if a >= b:
            return (window[0], window[0], window[2], window[2])
        a = lo + (a - lo) // step * step
        out += [a, min(a + -(-(b - a - 1) // step) * step + 1, hi)]
    return tuple(out)


def footprint_box(to_ref, shape: tuple[int, int], origin: tuple[int, int], margin: int = 16) -> tuple[int, int, int, int]:
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
        out.append(scene_xy(model, params, transform, window, f, ref, heights))
    return out


def output_grid(ref: xr.DataArray, to_ref: list, shapes: list, tile: int, nbands: int, heights: bool = False,
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


def store_attrs(summary: MosaicSummary, block: list[int], models: list, gains: np.ndarray) -> dict:
    """The store's attributes: the block's scenes, adjusted models, radiometry and summary (JSON)."""
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


__all__ = ["footprint_box", "load_models", "mosaic_tile", "output_crs", "output_grid", "scene_positions", "scene_to_map",
           "scene_xy", "shifted", "store_attrs", "through_map"]
