"""End-to-end polynomial registration on a real LocalCluster with Zarr stores on disk."""

import json

import numpy as np
import pytest
import xarray as xr
from conftest import read_band
from pairs import real_pair, tiepoint_errors

from geocoder import RegisterOptions, Status, register
from geocoder.kernels.polynomial import PolyMap
from geocoder.pipeline.detect import InterestOptions
from geocoder.scene import write_geotiff
from geocoder.simulate.warp import seed_affine_experiment

pytestmark = [pytest.mark.cluster, pytest.mark.data]


def _check_case(files, out, client, *, tile, resampling="bilinear"):
    ds = register(files.base, files.distorted, out=out, tile=tile, client=client, resampling=resampling, dense=False)
    pair = files.pair
    tp = xr.open_zarr(out, group="tiepoints", consolidated=False).compute()
    err = tiepoint_errors(tp, pair)
    inside = ds.status.values != Status.OUTSIDE
    rmse = float(np.sqrt(np.mean((ds.dx.values - pair.dx)[inside] ** 2 + (ds.dy.values - pair.dy)[inside] ** 2)))
    return ds, tp, err, rmse, inside


@pytest.mark.parametrize("which,size,tile", [("s2", 1024, 256), ("aerial", 576, 192)])
def test_polynomial_registration_real_imagery(shared_data, tmp_path, client, which, size, tile):
    files = real_pair(shared_data, tmp_path, which=which, size=size, seed=7)
    assert np.hypot(files.pair.dx, files.pair.dy).max() > 10  # a real distortion
    out = tmp_path / "out.zarr"
    ds, tp, err, rmse, inside = _check_case(files, out, client, tile=tile)
    n = tp.sizes["point"]
    assert n >= 100
    # spread: every cell of a 4 x 4 grid holds tie points
    cells = (tp.base_y.values * 4 // size) * 4 + tp.base_x.values * 4 // size
    assert len(np.unique(cells)) == 16
    assert err.max() <= 1.0, f"worst tie point {err.max():.3f} px from the truth"
    assert rmse <= 0.3, f"dx/dy RMSE {rmse:.3f} px"
    assert inside.mean() > 0.9
    # the store: registered bands on the base grid with the base CRS, documented status codes
    assert ds.registered.dims == ("band", "y", "x") and ds.registered.shape[1:] == (size, size)
    assert ds.rio.crs is not None and ds.dx.dtype == np.float32 and ds.status.dtype == np.uint8
    assert json.loads(ds.status.attrs["status_legend"])["model"] == Status.MODEL
    assert ds.status.attrs["flag_meanings"].split()[Status.MODEL] == "model"
    # the registered image matches the base where both exist
    reg, base = ds.registered.values[0], files.pair.base[0]
    ok = np.isfinite(reg) & inside
    assert np.corrcoef(reg[ok], base[ok])[0, 1] > 0.9


@pytest.mark.data
def test_seed_affine_experiment(shared_data, tmp_path, client):
    """Seed 000 sec. 4.5: B-bar up to 0.15, noise sigma 15 grey levels, 3x3 Hanning."""
    src = read_band(shared_data / "baviaanskloof/sentinel2_b432_byte.tif", 1, (300, 700, 200, 600))
    lo, hi = np.percentile(src, [1, 99])
    src = np.clip((src - lo) / (hi - lo), 0, 1) * 255  # the seed's images span the grey scale
    for seed in (1, 2, 3, 4, 5):
        pair = seed_affine_experiment(src, size=128, seed=seed)
        b, d = tmp_path / f"b{seed}.tif", tmp_path / f"d{seed}.tif"
        write_geotiff(b, pair.base)
        write_geotiff(d, pair.distorted)
        opts = RegisterOptions(interest=InterestOptions(cell=32), min_tiepoints=6)
        ds = register(b, d, tile=128, order=1, client=client, options=opts, dense=False)
        tp = ds.attrs["tiepoints"]
        inl = tp.inlier.values
        err = tiepoint_errors(tp, pair)
        assert inl.sum() >= 6
        assert np.abs(np.hypot(tp.residual_x.values, tp.residual_y.values)[inl]).max() <= 1.0
        assert err[inl].max() <= 1.0
        mapping = PolyMap.from_dict(json.loads(ds.attrs["mapping"]))
        jac = mapping.jacobian(np.array([64.0]), np.array([64.0]))[0]
        truth = np.eye(2) + pair.field.affine[:, :2]
        np.testing.assert_allclose(jac, truth, atol=0.01)


def test_reproducible_and_nearly_independent_of_tile_size(shared_data, tmp_path, client):
    """Same inputs give bitwise-equal output; another tiling changes dx/dy by < 0.01 px."""
    files = real_pair(shared_data, tmp_path, which="s2", size=512, seed=3)
    a = register(files.base, files.distorted, tile=256, client=client, dense=False)
    b = register(files.base, files.distorted, tile=256, client=client, dense=False)
    c = register(files.base, files.distorted, tile=128, client=client, dense=False)
    np.testing.assert_array_equal(a.dx.values, b.dx.values)
    np.testing.assert_array_equal(a.registered.values, b.registered.values)
    assert np.nanmax(np.abs(a.dx.values - c.dx.values)) < 0.01
    assert np.nanmax(np.abs(a.dy.values - c.dy.values)) < 0.01
    assert (a.status.values == c.status.values).mean() > 0.999


def test_real_pair_two_sensors_from_georeference(shared_data, tmp_path, client):
    """Pair B: Sentinel-2 B4 (10 m) <- Landsat 8 B4 (30 m, 24 bands), 10 days apart."""
    ds = register(
        shared_data / "baviaanskloof/sentinel2_b432_byte.tif", shared_data / "baviaanskloof/landsat8_byte.tif",
        out=tmp_path / "b.zarr", band=1, dist_band=4, client=client, dense=False,
    )
    s = json.loads(ds.attrs["summary"])
    assert s["coarse_method"].startswith("georeference")
    assert s["inliers"] >= 100 and s["rms"] < 0.5  # residuals in 30 m Landsat pixels
    assert ds.registered.sizes["band"] == 24 and ds.registered.shape[1:] == (1361, 797)
    # the mapping is close to the georeference: 1/3 scale, sub-pixel offset
    m = PolyMap.from_dict(json.loads(ds.attrs["mapping"]))
    jac = m.jacobian(np.array([400.0]), np.array([680.0]))[0]
    np.testing.assert_allclose(jac, np.eye(2) / 3, atol=0.01)
