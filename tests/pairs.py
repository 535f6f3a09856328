"""Test pairs (real images from ../shared/data or synthetic texture, warped by a known field,
written as GeoTIFFs) and comparisons of output stores."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import xarray as xr
import zarr
from affine import Affine
from conftest import read_band

from geocoder.scene import write_geotiff
from geocoder.simulate.texture import synthetic_ortho
from geocoder.simulate.warp import SyntheticPair, make_pair

S2_REF = "s2_arosics/ref_S2A_20160608T153121_T33UUU_sub.tif"
AERIAL = "baviaanskloof/ngi_rgb_byte_1.tif"
LANDSAT = "landsat7_rasterio/RGB.byte.tif"


@dataclass
class PairFiles:
    base: Path
    distorted: Path
    pair: SyntheticPair


def real_pair(shared: Path, out: Path, *, which: str, size: int, seed: int, margin: int = 32, **kw) -> PairFiles:
    """Crop a real image (no nodata inside), warp it with a known field, write both files.

    The base keeps the real georeference of the crop; the distorted file is a raw image
    (no georeference), as a scanner frame before geocoding. ``"landsat"``: dark sea with bright
    specks and the scene's nodata edge (0, made NaN) in the crop.
    """
    import rasterio

    if which == "s2":
        path, bands, origin = shared / S2_REF, [1], (300, 1100)
    elif which == "aerial":
        path, bands, origin = shared / AERIAL, [1, 2, 3], (60, 107)
    elif which == "landsat":
        path, bands, origin = shared / LANDSAT, [1], (300, 400)
    else:
        raise ValueError(which)
    r0, c0 = origin
    win = (r0, r0 + size + 2 * margin, c0, c0 + size + 2 * margin)
    src = np.stack([read_band(path, b, win) for b in bands])
    if which == "landsat":
        src = np.where(src > 0, src, np.nan).astype(np.float32)
    assert (src > 0).all() or which == "landsat", "the crop must be free of nodata"
    pair = make_pair(src, shape=(size, size), seed=seed, margin=margin, **kw)
    with rasterio.open(path) as f:
        t = f.transform @ Affine.translation(c0 + margin, r0 + margin)
        crs = f.crs
    out.mkdir(parents=True, exist_ok=True)
    base, dist = out / f"{which}-base.tif", out / f"{which}-distorted.tif"
    write_geotiff(base, pair.base, transform=t, crs=crs)
    write_geotiff(dist, pair.distorted)
    return PairFiles(base, dist, pair)


def tiepoint_errors(tp, pair: SyntheticPair) -> np.ndarray:
    """Distance of every tie point's distorted position from the truth."""
    bx, by = np.asarray(tp["base_x"]), np.asarray(tp["base_y"])
    tx, ty = pair.field.displacement(bx, by)
    return np.hypot(np.asarray(tp["dist_x"]) - bx - tx, np.asarray(tp["dist_y"]) - by - ty)


def write_synthetic_pair(directory: Path, size: int, *, seed: int, max_displacement: float, margin: int = 48) -> Path:
    """``base.tif`` (georeferenced, UTM 33N, 2 m) and ``dist.tif`` (raw) of a synthetic texture."""
    src = synthetic_ortho((size + 2 * margin,) * 2, seed=seed)
    pair = make_pair(src, shape=(size, size), seed=seed, max_displacement=max_displacement, margin=margin)
    write_geotiff(directory / "base.tif", pair.base, transform=Affine(2, 0, 500000, 0, -2, 4000000), crs="EPSG:32633")
    write_geotiff(directory / "dist.tif", pair.distorted)
    return directory


def load_output(store) -> dict[str, np.ndarray]:
    """Every variable of a register output store, the tie points' under ``tiepoints/``.

    Read by this process (no dask), whatever Client happens to be the default.
    """
    ds = xr.open_zarr(store, consolidated=False, chunks=None)
    out = {k: ds[k].values for k in ds.data_vars}
    tp = xr.open_zarr(store, group="tiepoints", consolidated=False, chunks=None)
    out.update({f"tiepoints/{k}": tp[k].values for k in tp.data_vars})
    return out


def assert_identical(a: dict, b: dict) -> None:
    """Same variables, dtypes, shapes and values, bit for bit (NaN equal to NaN)."""
    assert sorted(a) == sorted(b)
    for k in a:
        assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, k
        assert np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f"), f"{k} differs"


def legacy_codec_copy(src, dst: Path) -> Path:
    """Copy a store (a path, or an open group: one level of a store), arrays gzip-compressed and the array-to-bytes codec named ``endian``.

    GDAL up to at least 3.10 knows the v3 draft's name ``endian`` (the v3.0 spec renamed it
    ``bytes``) and no ``zstd``; the copy differs from ``src`` in those two names only, so GDAL
    reads the attributes and coordinate arrays geocoder wrote.
    """
    source = src if isinstance(src, zarr.Group) else zarr.open_group(src, mode="r")
    target = zarr.open_group(dst, mode="w", zarr_format=3, attributes=source.attrs.asdict())
    for name, array in source.arrays():
        copy = target.create_array(name, shape=array.shape, dtype=array.dtype, chunks=array.chunks,
                                   dimension_names=array.metadata.dimension_names, attributes=array.attrs.asdict(),
                                   compressors=zarr.codecs.GzipCodec(), fill_value=array.fill_value)
        copy[...] = array[...]
    for meta in dst.rglob("zarr.json"):
        doc = json.loads(meta.read_text())
        for codec in doc.get("codecs", []):
            if codec["name"] == "bytes":
                codec["name"] = "endian"
        meta.write_text(json.dumps(doc))
    return dst
