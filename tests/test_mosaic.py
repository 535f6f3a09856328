"""Mosaic of a 2 x 2 block: scenes found on a reference, block adjustment, one seamless grid.

Truth: every scene is the reference orthoimage seen through a known mapping ``T_k`` (scene
pixel -> ortho pixel: rotation, scale, a quadratic term, new noise and gain;
:mod:`geocoder.simulate.block`), so the error of an output pixel taken from scene ``k`` is
``|T_k(model_k(p)) - p|`` in output pixels (:func:`geocoder.quality.accuracy.mosaic_errors`).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from affine import Affine

from geocoder.mosaic import mosaic
from geocoder.quality.accuracy import mosaic_errors
from geocoder.scene import world_to_pixel, write_geotiff
from geocoder.simulate.block import BlockScene, render
from geocoder.simulate.texture import synthetic_ortho
from geocoder.status import Status

pytestmark = pytest.mark.cluster

ORTHO = Affine(2.0, 0.0, 500000.0, 0.0, -2.0, 5800000.0)
SIZE = 320
# a 2 x 2 block, 40 % overlap, each scene rotated, scaled, bent and re-exposed differently
SCENES = [
    BlockScene(row0=r0, col0=c0, size=SIZE, angle_deg=a, scale=s, quadratic_px=q, gain=1.1 + 0.05 * k, offset=3.0 * k)
    for k, ((r0, c0), a, s, q) in enumerate(zip([(96, 96), (96, 288), (288, 96), (288, 288)], [2.0, -3.0, 1.5, -1.0],
                                                [1.0, 1.02, 0.98, 1.01], [1.5, -2.0, 1.0, 2.5]))
]


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    d = tmp_path_factory.mktemp("block")
    ortho = np.squeeze(synthetic_ortho((768, 768), seed=21)).astype(np.float32)
    write_geotiff(d / "ortho.tif", ortho, transform=ORTHO, crs="EPSG:32633")
    paths = []
    for k, scene in enumerate(SCENES):
        paths.append(d / f"scene{k}.tif")
        write_geotiff(paths[-1], render(ortho, scene, seed=k))  # no georeference: found on the reference
    # on the reference (georeferenced: a small scene at the reference's edge defeats the blind
    # coarse alignment), overlapping no other scene
    write_geotiff(d / "far.tif", ortho[620:760, 20:180], transform=ORTHO * Affine.translation(20, 620), crs="EPSG:32633")
    rng = np.random.default_rng(3)
    write_geotiff(d / "noise.tif", rng.normal(100, 20, (200, 200)).astype(np.float32))  # not on the reference
    return d, paths


def errors(ds) -> tuple[np.ndarray, np.ndarray]:
    scenes = [SCENES[int(s.rsplit("scene", 1)[1][0])] for s in json.loads(ds.attrs["scenes"])]
    return mosaic_errors(ds, [s.to_ortho for s in scenes], [(SIZE, SIZE)] * len(scenes), ORTHO)


def test_block_mosaic_against_truth(block, client, tmp_path):
    d, paths = block
    out = tmp_path / "mosaic.zarr"
    ds = mosaic(paths, reference=d / "ortho.tif", out=out, tile=128, client=client)
    s = json.loads(ds.attrs["summary"])
    assert s["left_out"] == {} and len(s["pairs"]) == 6
    assert all(0.05 <= p["overlap"] <= 1.0 for p in s["pairs"])  # reported: the share of i inside j
    assert int(s["rays"].get("3", 0)) > 0  # multi-ray ties: one point seen in three scenes
    assert ds.rio.crs.to_epsg() == 32633
    own, seam = errors(ds)
    valid = np.isfinite(own)
    assert valid.mean() > 0.5
    rmse = float(np.sqrt(np.mean(own[valid] ** 2)))
    assert rmse < 0.1, rmse
    assert np.nanmax(own) < 0.5
    assert float(np.sqrt(np.mean(seam**2))) < 0.2  # neighbours agree wherever they overlap
    # every source pixel has a value; uncovered pixels have none
    covered = ds.source.values != 65535
    assert np.isfinite(ds.mosaic.values[0][covered]).all() and np.isnan(ds.mosaic.values[0][~covered]).all()
    # radiometric balance: scenes rendered with gains 1.10-1.25 and offsets 0-9 come back to the reference's grey values
    import rioxarray

    ortho = rioxarray.open_rasterio(d / "ortho.tif").values[0]
    ex, ny = np.meshgrid(ds.x.values, ds.y.values)
    gx, gy = (np.rint(v).astype(int) for v in world_to_pixel(ORTHO, ex, ny))
    diff = (ds.mosaic.values[0] - ortho[gy, gx])[covered]
    assert float(np.sqrt(np.mean(diff**2))) < 0.05 * float(ortho.std())
    before, after = s["seam_step"]
    assert after < 0.2 * before
    gains = np.array(json.loads(ds.attrs["radiometry"]))[:, 0]
    np.testing.assert_allclose(gains[:, 0], 1 / (1.1 + 0.05 * np.arange(4)), rtol=0.02)
    # per-point precision (a block this small has the covariances) and what the adjustment left out
    import xarray as xr

    points = xr.open_zarr(out, group="points", consolidated=False)
    tie = points.control.values == 0
    assert tie.sum() > 50 and np.mean(points.rays.values[tie] >= 2) > 0.95  # a tie seen once: its other ray left out
    sigma = np.fmax(points.sigma_x.values, points.sigma_y.values)
    assert np.isfinite(sigma).all() and np.isfinite(points.max_w.values).any()
    median, p95, largest = s["point_sigma_px"]["tie"]
    assert 0.0 < median <= p95 <= largest < 0.5 and median < 0.05, s["point_sigma_px"]
    assert median == pytest.approx(float(np.median(sigma[tie])), rel=1e-3)
    # a tie point seen in three scenes is placed better than the median one seen in two
    assert np.median(sigma[tie & (points.rays.values >= 3)]) < np.median(sigma[tie & (points.rays.values == 2)])
    assert set(s["rejected"]) == {"robust", "snooping"} and min(s["rejected"].values()) >= 0
    assert np.nanmax(points.max_w.values[tie]) < 3.29 + 1e-6 or s["rejected"]["snooping"] == 10  # snooped to the bound


@pytest.fixture(scope="module")
def sparse_cli(block, client, tmp_path_factory):
    """The command line's mosaic of the block, the scene far from the others and the noise, with
    control on scene 0 only (and scene 5, which the reference cannot find: none), and its COG.

    ``test_sparse_control_is_carried_by_tie_points`` checks its figures,
    ``test_cli_mosaic_and_blend_kernel`` the command and its files: one job for both.
    """
    import subprocess
    import sys

    d, paths = block
    out = tmp_path_factory.mktemp("sparse-cli")
    scenes = [*paths, d / "far.tif", d / "noise.tif"]
    r = subprocess.run([sys.executable, "-m", "geocoder.cli", "-q", "mosaic", *map(str, scenes), "--reference", str(d / "ortho.tif"),
                        "--out", str(out / "m.zarr"), "--tile", "128", "--control-scenes", "0,5",
                        "--cog", str(out / "m.tif"), "--scheduler", client.scheduler.address],
                       capture_output=True, text=True, timeout=600)
    return out, r


def test_sparse_control_is_carried_by_tie_points(sparse_cli):
    """Control on one corner scene only: the tie points place the other three (seed 000 Table 5's point)."""
    import xarray as xr

    out, r = sparse_cli
    assert r.returncode == 0, r.stderr
    ds = xr.open_zarr(out / "m.zarr", decode_coords="all", consolidated=False)
    s = json.loads(ds.attrs["summary"])
    assert s["control_points"][1:4] == [0, 0, 0]
    # reported and left out, never silently warped: one has no tie to a controlled scene, one is not on the reference
    assert sorted(s["left_out"]) == ["4", "5"]
    assert "tied to no control point" in s["left_out"]["4"] and "not found on the reference" in s["left_out"]["5"]
    assert len(json.loads(ds.attrs["scenes"])) == 4
    own, seam = errors(ds)
    print("sparse control: rmse", float(np.sqrt(np.nanmean(own**2))), "seam rms", float(np.sqrt(np.mean(seam**2))))
    assert float(np.sqrt(np.nanmean(own**2))) < 0.3
    assert float(np.sqrt(np.mean(seam**2))) < 0.2


def test_cli_mosaic_and_blend_kernel(sparse_cli):
    from geocoder.mosaic.compose import NO_SOURCE, blend

    tmp_path, r = sparse_cli
    assert r.returncode == 0, r.stderr
    assert "overlapping pairs: 6" in r.stdout and "control points per scene" in r.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.tif", "m.zarr"]
    # the COG: the store's pixels, CRS and transform, overviews, valid for rio-cogeo
    import rasterio
    import xarray as xr
    from rio_cogeo.cogeo import cog_validate

    store = xr.open_zarr(tmp_path / "m.zarr", decode_coords="all", consolidated=False)
    assert store.rio.crs == "EPSG:32633" and store.attrs["proj:code"] == "EPSG:32633"
    with rasterio.open(tmp_path / "m.tif") as f:
        assert f.crs == store.rio.crs and f.transform == store.rio.transform()
        np.testing.assert_array_equal(f.read(), store.mosaic.values)
        assert f.overviews(1)
    assert cog_validate(str(tmp_path / "m.tif"), strict=True)[0]
    # the blend: weights sum to one where covered, the lowest score is the source, feathered across the seam
    scores = np.array([[[0.2, 0.50, 0.52, 0.9]], [[0.9, 0.52, 0.50, np.nan]]])
    values = np.stack([np.full((1, 1, 4), 10.0), np.full((1, 1, 4), 20.0)])
    mosaic_, source, weight = blend(values, scores, feather=0.1)
    np.testing.assert_array_equal(source[0], [0, 0, 1, 0])
    np.testing.assert_allclose(weight.sum(axis=0)[0], 1.0)
    np.testing.assert_allclose(mosaic_[0, 0], [10.0, 10 * 1 / 1.8 + 20 * 0.8 / 1.8, 10 * 0.8 / 1.8 + 20 / 1.8, 10.0], rtol=1e-6)
    m, s, _ = blend(values, np.full((2, 1, 4), np.nan), feather=0.1)
    assert np.isnan(m).all() and (s == NO_SOURCE).all()


def test_dense_refinement_follows_scan_line_turbulence(client, tmp_path):
    """Airborne strips whose lines are shifted by roll and pitch (up to 1.5 px, changing over
    tens of lines): no polynomial follows that; the dense refinement against the reference does."""
    from geocoder.mosaic import scene_positions

    ortho = np.squeeze(synthetic_ortho((640, 640), seed=23)).astype(np.float32)
    write_geotiff(tmp_path / "ortho.tif", ortho, transform=ORTHO, crs="EPSG:32633")
    scenes = [BlockScene(row0=120, col0=c0, size=SIZE, angle_deg=a, scale=1.0, quadratic_px=q, gain=1.0 + 0.1 * k,
                         offset=2.0 * k, turbulence_px=1.5, turbulence_seed=k)
              for k, (c0, a, q) in enumerate([(96, 1.5, 1.0), (224, -2.0, -1.5)])]
    paths = []
    for k, scene in enumerate(scenes):
        paths.append(tmp_path / f"strip{k}.tif")
        write_geotiff(paths[-1], render(ortho, scene, seed=k))
    figures = {}
    out = tmp_path / "m-dense.zarr"
    ds = mosaic(paths, reference=tmp_path / "ortho.tif", out=out, tile=128, client=client, dense=True)
    assert len(json.loads(ds.attrs["scenes"])) == 2
    # the model only: the same mosaic's adjusted models (the block adjustment does not depend on
    # ``dense``: a dense=False job's models are these, to the digit) at the pixels each strip is the
    # source of; dense: the positions the mosaic sampled (its fields where refined)
    for dense, positions in ((False, None), (True, scene_positions(ds, out))):
        own, seam = mosaic_errors(ds, [s.to_ortho for s in scenes], [(SIZE, SIZE)] * 2, ORTHO, positions=positions)
        own = own[np.isfinite(own)]
        figures[dense] = (float(np.sqrt(np.mean(own**2))), float(np.sqrt(np.mean(seam**2))), float(np.mean(own > 1.0)))
    # on another CRS (UTM zone 34, 6 degrees west) at another pixel (3 m): the fields sampled where the
    # output pixels fall on the reference's grid
    out = tmp_path / "m-utm34.zarr"
    ds = mosaic(paths, reference=tmp_path / "ortho.tif", out=out, tile=128, client=client, dense=True,
                crs="EPSG:32634", resolution=3.0)
    assert ds.rio.crs.to_epsg() == 32634 and ds.rio.transform().a == 3.0
    err = _reprojected_errors(ds, out, scenes)
    figures["utm34"] = (float(np.sqrt(np.nanmean(err**2))), float(np.nanmean(err > 1.0)))
    print("model only (rmse, seam rms, share > 1 px):", figures[False], "dense:", figures[True],
          "dense on EPSG:32634 at 3 m (rmse, share > 1 output px):", figures["utm34"])
    assert figures[False][0] > 0.5  # the turbulence is there, and the models cannot follow it
    assert figures[True][0] <= 0.3
    assert figures[True][1] <= 0.2
    assert figures[True][0] < figures[False][0] / 2
    assert np.isfinite(err).mean() > 0.4 and figures["utm34"][0] <= 0.3 * 2 / 3  # 3 m output pixels
    status = ds.status.values[np.isfinite(err)]
    assert np.mean((status == Status.MATCHED) | (status == Status.FILLED) | (status == Status.ESTIMATED)) > 0.9


def _reprojected_errors(ds, store, scenes) -> np.ndarray:
    """Per covered output pixel of a mosaic on another grid, its distance (output px) from where the
    truth puts the scene position the mosaic sampled there; NaN elsewhere."""
    from pyproj import Transformer

    from geocoder.geometry import pixel_to_world, world_to_pixel
    from geocoder.mosaic import scene_positions

    to_out = Transformer.from_crs("EPSG:32633", ds.rio.crs, always_xy=True)
    src = ds.source.values
    rows, cols = np.indices(src.shape)
    err = np.full(src.shape, np.nan)
    for n, (x, y) in enumerate(scene_positions(ds, store)):
        sel = src == n
        c, r = world_to_pixel(ds.rio.transform(), *to_out.transform(*pixel_to_world(ORTHO, *scenes[n].to_ortho(x[sel], y[sel]))))
        err[sel] = np.hypot(c - cols[sel], r - rows[sel])
    return err


def test_check_points_are_withheld_and_reported(block, tmp_path, client):
    """Every 4th control point withheld: the adjustment does not see them, their residuals
    through the adjusted models are reported, as small as the adjustment's own."""
    d, paths = block
    ds = mosaic(paths[:2], reference=d / "ortho.tif", tile=128, client=client, check_points=0.25, balance=False)
    s = json.loads(ds.attrs["summary"])
    print("check points", s["check_points"], s["check_rmse_px"], "control", s["control_points"], "rms", s["rms_px"])
    assert all(n > 10 for n in s["check_points"])
    assert all(n >= 2 * c for n, c in zip(s["control_points"], s["check_points"]))  # 3 of 4 still used
    assert all(0.0 < r < 0.1 for r in s["check_rmse_px"])
