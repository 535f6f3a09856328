"""The mosaic's per-pixel layers ``status``, ``sigma_x``, ``sigma_y`` against the simulator's truth.

The block is test_mosaic's pair of airborne strips with scan-line turbulence, refined densely;
control on the first strip only, so the second is placed by tie points and, with
``dense="control"`` (no refinement against the neighbours), keeps its model: the
mosaic has pixels from a dense field (matched and filled), from a model only, and from no scene.
The error of an output pixel is ``T_k(position in scene k) - p`` per axis (output pixels).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import xarray as xr
import zarr
from test_mosaic import ORTHO, SIZE

from geocoder.conventions import status_attrs
from geocoder.mosaic import mosaic, scene_positions
from geocoder.scene import world_to_pixel, write_geotiff
from geocoder.simulate.block import BlockScene, render
from geocoder.simulate.texture import synthetic_ortho
from geocoder.status import Status

pytestmark = pytest.mark.cluster

STRIPS = [BlockScene(row0=120, col0=c0, size=SIZE, angle_deg=a, scale=1.0, quadratic_px=q, gain=1.0 + 0.1 * k,
                     offset=2.0 * k, turbulence_px=1.5, turbulence_seed=k)
          for k, (c0, a, q) in enumerate([(96, 1.5, 1.0), (224, -2.0, -1.5)])]
#: Two output tilings: the layers must not depend on them.
OUTPUT_TILES = (128, 80)


@pytest.fixture(scope="module")
def strips(tmp_path_factory, client):
    d = tmp_path_factory.mktemp("layers")
    ortho = np.squeeze(synthetic_ortho((640, 640), seed=23)).astype(np.float32)
    write_geotiff(d / "ortho.tif", ortho, transform=ORTHO, crs="EPSG:32633")
    paths = []
    for k, scene in enumerate(STRIPS):
        paths.append(d / f"strip{k}.tif")
        write_geotiff(paths[-1], render(ortho, scene, seed=k))
    runs = {}
    for t in OUTPUT_TILES:
        out = d / f"m{t}.zarr"
        runs[t] = (mosaic(paths, reference=d / "ortho.tif", out=out, tile=128, output_tile=t, client=client, dense="control",
                          control_scenes=[0]), out)
    return runs


def true_errors(ds: xr.Dataset, store) -> np.ndarray:
    """``(2, y, x)``: the position error of every output pixel in its source scene, per axis (NaN where none)."""
    ex, ny = np.meshgrid(ds.x.values, ds.y.values)
    gx, gy = world_to_pixel(ORTHO, ex, ny)
    src = ds.source.values
    err = np.full((2, *src.shape), np.nan)
    for n, (x, y) in enumerate(scene_positions(ds, store)):
        own = src == n
        tx, ty = STRIPS[n].to_ortho(x[own], y[own])
        err[0][own], err[1][own] = tx - gx[own], ty - gy[own]
    return err


def test_status_says_where_each_position_came_from(strips):
    ds, store = strips[OUTPUT_TILES[0]]
    assert json.loads(ds.attrs["scenes"])[0].endswith("strip0.tif")
    status, source = ds.status.values, ds.source.values
    sx, sy = ds.sigma_x.values, ds.sigma_y.values
    assert ds.status.dtype == np.uint8 and ds.sigma_x.dtype == np.float32
    attrs = status_attrs()
    assert ds.status.attrs["flag_meanings"] == attrs["flag_meanings"]
    np.testing.assert_array_equal(ds.status.attrs["flag_values"], attrs["flag_values"])
    # no scene: outside, no sigma; every covered pixel has a finite sigma
    np.testing.assert_array_equal(status == Status.OUTSIDE, source == 65535)
    assert (source == 65535).any()
    assert np.isnan(sx[source == 65535]).all() and np.isnan(sy[source == 65535]).all()
    covered = source != 65535
    assert np.isfinite(sx[covered]).all() and np.isfinite(sy[covered]).all()
    # the strip without control has no dense field: its model's
    assert (status[source == 1] == Status.MODEL).all() and (source == 1).sum() > 10_000
    # the refined strip: the status of its field at the pixel (field OUTSIDE, or no field there: the model's)
    field = zarr.open_group(f"{store}/dense/0", mode="r")
    f0 = field.attrs
    col0, row0 = json.loads(ds.attrs["reference_origin"])
    rows, cols = np.nonzero(source == 0)
    fr, fc = rows + row0 - f0["row0"], cols + col0 - f0["col0"]
    fst = np.asarray(field["status"][:])
    inside = (fr >= 0) & (fr < fst.shape[0]) & (fc >= 0) & (fc < fst.shape[1])
    expected = np.full(rows.size, Status.MODEL, dtype=np.uint8)
    expected[inside] = fst[fr[inside], fc[inside]]
    expected[expected == Status.OUTSIDE] = Status.MODEL
    np.testing.assert_array_equal(status[rows, cols], expected)
    counts = np.bincount(status[source == 0], minlength=len(Status))
    assert counts[Status.MATCHED] > 0.8 * rows.size and counts[Status.FILLED] > 0
    # the overview levels carry the layers: status by the nearest (top-left) pixel, sigma averaged
    level = xr.open_zarr(store, group="1", consolidated=False)
    np.testing.assert_array_equal(level.status.values, status[::2, ::2])
    assert level.status.attrs["flag_meanings"] == attrs["flag_meanings"]
    assert "sigma_x" in level and "sigma_y" in level and level.sigma_x.attrs["units"] == "pixel"


def test_sigma_is_calibrated_against_the_true_error(strips):
    ds, store = strips[OUTPUT_TILES[0]]
    err = true_errors(ds, store)
    status = ds.status.values
    sigma = np.stack([ds.sigma_x.values, ds.sigma_y.values])
    ratios = {}
    for code in (Status.MATCHED, Status.FILLED, Status.MODEL):
        m = (status == code) & np.isfinite(err[0])
        rmse = np.sqrt(np.mean(err[:, m] ** 2, axis=1))
        rms_sigma = np.sqrt(np.mean(sigma[:, m].astype(np.float64) ** 2, axis=1))
        ratios[code.name] = (rmse / rms_sigma).round(2).tolist()
        print(f"{code.name}: {m.sum()} px, RMSE x/y {rmse.round(3)}, RMS sigma x/y {rms_sigma.round(3)}, "
              f"ratio {ratios[code.name]}")
    # the block's model (turbulence it cannot follow, in its residuals) and the corrections carried from matches
    for name in ("MODEL", "FILLED"):
        assert all(0.5 <= r <= 2.0 for r in ratios[name]), (name, ratios)
    # the dense match's own sigma: the matcher's claim, optimistic where the turbulence varies inside its
    # 51 x 7 template (the README's error analysis found 1-5x); still within a factor of four
    assert all(1.0 <= r <= 4.0 for r in ratios["MATCHED"]), ratios


def test_layers_do_not_depend_on_the_output_tile(strips):
    (a, _), (b, _) = (strips[t] for t in OUTPUT_TILES)
    assert a.status.encoding["chunks"] != b.status.encoding["chunks"]
    np.testing.assert_array_equal(a.source.values, b.source.values)
    np.testing.assert_array_equal(a.status.values, b.status.values)
    for name in ("sigma_x", "sigma_y"):
        np.testing.assert_allclose(a[name].values, b[name].values, rtol=1e-6, equal_nan=True)
