"""Rendering synthetic scanner images from a real ortho and a DEM, with per-pixel truth."""

import numpy as np
import pytest
from conftest import read_band

from geocoder.geometry import pixel_to_world
from geocoder.kernels.resample import sample
from geocoder.pipeline.simulate import Radiometry, load_sensor, load_terrain, simulate
from geocoder.simulate.satellite import geodetic_to_ecef

pytestmark = [pytest.mark.cluster, pytest.mark.data]
NGI = "baviaanskloof/ngi_rgb_byte_1.tif"


def sampled_back(ds, ortho, transform, *, satellite=False, step=3):
    """Ortho pixels (every ``step``-th) -> ground (DEM height) -> image (direct mode) -> rendered value there."""
    sensor, terrain = load_sensor(ds), load_terrain(ds)
    h, w = ortho.shape
    ys, xs = np.mgrid[8 : h - 8 : step, 8 : w - 8 : step].astype(float)
    X, Y = pixel_to_world(transform, xs, ys)
    Z = terrain(X, Y)
    if satellite:
        from pyproj import Transformer

        lon, lat = Transformer.from_crs(ds.attrs["crs"], "EPSG:4326", always_xy=True).transform(X, Y)
        X, Y, Z = geodetic_to_ecef(np.deg2rad(lat), np.deg2rad(lon), Z)
    row, col = sensor.ground_to_image(X, Y, Z)
    img = ds.image.values[0]
    vals = sample(img, col, row, method="cubic")
    ok = np.isfinite(vals) & (ortho[ys.astype(int), xs.astype(int)] > 0)
    return vals[ok], ortho[ys.astype(int), xs.astype(int)][ok]


@pytest.mark.parametrize("sensor", ["atm", "asas"])
def test_airborne_render_reproduces_ortho(shared_data, tmp_path, client, sensor):
    import rasterio

    path = shared_data / NGI
    ortho = read_band(path, 1)
    transform = rasterio.open(path).transform
    kw = dict(band=1, sensor=sensor, relief=150.0, seed=4, client=client, tile=256, turbulence_deg=0.2,
              tilt_deg=30.0 if sensor == "asas" else 0.0)
    clean = simulate("airborne", path, out=tmp_path / "clean.zarr", radiometry=Radiometry(noise=0.0), **kw)
    noisy = simulate("airborne", path, out=tmp_path / "noisy.zarr", radiometry=Radiometry(noise=0.02), **kw)
    v0, o0 = sampled_back(clean, ortho, transform)
    v1, o1 = sampled_back(noisy, ortho, transform)
    assert v0.size > 10000
    rms0 = np.sqrt(np.mean((v0 - o0) ** 2))
    rms1 = np.sqrt(np.mean((v1 - o1) ** 2))
    lo, hi = np.percentile(ortho[ortho > 0], [1, 99])
    sigma = 0.02 * (hi - lo)
    print(sensor, rms0, rms1, sigma, np.std(o0))
    assert rms0 < 0.25 * np.std(o0)  # only interpolation (twice) is left without noise
    assert np.sqrt(max(rms1**2 - rms0**2, 0)) == pytest.approx(sigma, rel=0.25)
    # truth: ground coordinates of a pixel agree with the inverse mode, heights with the DEM
    terrain = load_terrain(clean)
    gx, gy, gz = (clean[k].values for k in ("ground_x", "ground_y", "ground_z"))
    np.testing.assert_allclose(gz[::50, ::50], terrain(gx[::50, ::50], gy[::50, ::50]), atol=1e-3)


def test_satellite_render_and_seed(shared_data, tmp_path, client):
    import rasterio

    path = shared_data / "s2_arosics/ref_S2A_20160608T153121_T33UUU_sub.tif"
    kw = dict(relief=300.0, client=client, tile=256, radiometry=Radiometry(noise=0.0))
    a = simulate("satellite", path, out=tmp_path / "a.zarr", seed=1, pixel=30.0, **kw)
    # the seed decides everything (on 60 m pixels, a quarter of the work)
    b1, b2, c = (simulate("satellite", path, out=tmp_path / f"{name}.zarr", seed=seed, pixel=60.0, **kw)
                 for name, seed in (("b1", 1), ("b2", 1), ("c", 2)))
    np.testing.assert_array_equal(b1.image.values, b2.image.values)
    np.testing.assert_array_equal(b1.ground_x.values, b2.ground_x.values)
    assert not np.array_equal(b1.ground_x.values, c.ground_x.values)
    ortho = read_band(path, 1)
    # 30 m image pixels on the 10 m ortho: every 6th ortho pixel is every 2nd image pixel (~210,000 points)
    v, o = sampled_back(a, ortho, rasterio.open(path).transform, satellite=True, step=6)
    assert v.size > 10000
    assert np.sqrt(np.mean((v - o) ** 2)) < 0.25 * np.std(o)
    # the truth in the ortho CRS: back to ECEF and into the image gives the pixel itself
    sensor = load_sensor(a)
    rows, cols = np.mgrid[0 : a.sizes["y"] : 97, 0 : a.sizes["x"] : 89]
    gx, gy, gz = (a[k].values[rows, cols] for k in ("ground_x", "ground_y", "ground_z"))
    from pyproj import Transformer

    lon, lat = Transformer.from_crs(a.attrs["crs"], "EPSG:4326", always_xy=True).transform(gx, gy)
    r, cc = sensor.ground_to_image(*geodetic_to_ecef(np.deg2rad(lat), np.deg2rad(lon), gz))
    np.testing.assert_allclose(r, rows, atol=1e-4)
    np.testing.assert_allclose(cc, cols, atol=1e-4)
