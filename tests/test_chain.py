"""``register --via``: a 45 degree look registered onto nadir through a 30 degree look (seed 003 sec. 10).

Three ASAS-like looks of the simulator over the same real orthophoto and DEM; the truth of
every nadir pixel is where the 45 degree sensor sees its ground point.
"""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import rasterio
import xarray as xr
from affine import Affine
from rasterio.windows import Window

from geocoder import Status
from geocoder.kernels.resample import sample
from geocoder.pipeline.simulate import load_sensor, simulate
from geocoder.scene import write_geotiff
from geocoder.simulate.terrain import fractal_dem

pytestmark = [pytest.mark.cluster, pytest.mark.data]
NGI = "baviaanskloof/ngi_rgb_byte_1.tif"


def look_truth(base: str, distorted: str) -> tuple[np.ndarray, np.ndarray]:
    """True ``d = p_distorted - p_base`` on the base look's grid, from the simulator's ground truth."""
    b = xr.open_zarr(base, consolidated=False)
    sensor = load_sensor(xr.open_zarr(distorted, consolidated=False))
    gx, gy, gz = (b[k].values for k in ("ground_x", "ground_y", "ground_z"))
    row, col = sensor.ground_to_image(gx, gy, gz)
    ys, xs = np.mgrid[0 : gx.shape[0], 0 : gx.shape[1]]
    return col - xs, row - ys


@pytest.fixture(scope="module")
def looks(shared_data, tmp_path_factory, client):
    """Nadir, 30 and 45 degree looks (512 x 256 px) over a 400 x 400 px crop of a real ortho and one DEM."""
    d = tmp_path_factory.mktemp("looks")
    with rasterio.open(shared_data / NGI) as f:
        img = f.read(1, window=Window(150, 400, 400, 400))
        transform, crs = f.transform * Affine.translation(150, 400), f.crs.to_wkt()
    write_geotiff(d / "ortho.tif", img, transform=transform, crs=crs, nodata=0)
    write_geotiff(d / "dem.tif", fractal_dem((100, 100), seed=7, relief=25.0).astype(np.float32),
                  transform=transform * Affine.scale(4), crs=crs)
    paths = {}
    for tilt, seed in ((0, 1), (30, 2), (45, 3)):
        paths[tilt] = str(d / f"look{tilt}.zarr")
        simulate("airborne", d / "ortho.tif", dem=d / "dem.tif", out=paths[tilt], sensor="asas", tilt_deg=tilt, rows=256,
                 seed=seed, turbulence_deg=0.05, tile=256, client=client)
    return paths


def test_register_via_middle_look_against_truth(looks, tmp_path, client):
    out = tmp_path / "via.zarr"
    r = subprocess.run([sys.executable, "-m", "geocoder.cli", "-q", "register", looks[0], looks[45], "--via", looks[30],
                        "--out", str(out), "--tile", "256", "--scheduler", client.scheduler.address],
                       capture_output=True, text=True, timeout=600, check=False)
    assert r.returncode == 0, r.stderr
    assert "[first leg" in r.stdout and "[second leg" in r.stdout and f"wrote {out}" in r.stdout
    assert [p for p in os.listdir(tmp_path) if p.startswith(".")] == []  # the legs' job directory is gone
    ds = xr.open_zarr(out, consolidated=False)
    chain = json.loads(ds.attrs["chain"])
    assert chain["via"] == looks[30] and chain["first"]["tiepoints"] > 50 and chain["second"]["tiepoints"] > 50
    tx, ty = look_truth(looks[0], looks[45])
    status = ds.status.values
    matched = status == Status.MATCHED
    inside = status != Status.OUTSIDE
    err = np.hypot(ds.dx.values - tx, ds.dy.values - ty)
    rmse_matched = float(np.sqrt(np.mean(err[matched] ** 2)))
    median_inside = float(np.median(err[inside]))
    print(f"coverage {matched.sum() / inside.sum():.3f}, RMSE matched {rmse_matched:.3f} px, median {median_inside:.3f} px")
    assert inside.mean() > 0.9
    assert matched.sum() / inside.sum() > 0.6
    assert rmse_matched < 0.8  # the legs are ~0.3 px each, mostly along track (relief parallax)
    assert median_inside < 0.5
    # sigma: propagated through both legs, finite where matched
    sy = ds.sigma_y.values[matched]
    assert np.isfinite(sy).all()
    assert np.sqrt(np.mean(sy**2)) > 0.03
    # one resampling of the ORIGINAL 45 degree image at p + d(p)
    image = xr.open_zarr(looks[45], consolidated=False).image.values[0]
    ys, xs = np.mgrid[0 : status.shape[0], 0 : status.shape[1]].astype(np.float64)
    expected = sample(image, xs + ds.dx.values.astype(np.float64), ys + ds.dy.values.astype(np.float64), method="bilinear")
    reg = ds.registered.values[0]
    ok = np.isfinite(expected) & inside
    np.testing.assert_allclose(reg[ok], expected[ok], rtol=1e-5, atol=1e-3)
    assert (status[~np.isfinite(reg)] == Status.OUTSIDE).all()
