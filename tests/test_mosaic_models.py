"""Mosaic with per-scene sensor models and a DEM: line scanners over relief, against truth.

Truth: a 2 x 2 block of 256² push-broom scenes (:mod:`geocoder.simulate.linescanner_block`) rendered
over a real Sentinel-2 crop (10 m) and a fractal DEM of 300 m relief, rolled 0.35 rad off
nadir (the left column from one side, the right from the other), so relief displaces pixels
by up to ~11 px, differently in neighbouring scenes. Every scene carries its navigation (the
true scanner with position and attitude offsets of ~15 m and ~1e-5 rad) as a line-scanner tag
and as RPCs. The error of an output pixel taken from scene ``k`` at scene position ``q`` is
``|T_k(q) - p|`` in output pixels, ``T_k`` the ray of ``q`` intersected with the true DEM.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from affine import Affine

from geocoder.errors import InputError
from geocoder.mosaic import mosaic, scene_positions
from geocoder.mosaic.projection import project_window
from geocoder.mosaic.sensors import model_from_dict, model_to_dict, scene_sensor, sensor_model
from geocoder.quality.accuracy import mosaic_errors
from geocoder.simulate.linescanner_block import line_scanner_block

S2 = "s2_arosics/ref_S2A_20160608T153121_T33UUU_sub.tif"
SIZE = 256


@pytest.fixture(scope="module")
def relief_block(shared_data, tmp_path_factory):
    import rasterio

    with rasterio.open(shared_data / S2) as src:
        r0, c0, ext = 300, 900, 560  # east of the no-data wedge
        ortho = src.read(1, window=((r0, r0 + ext), (c0, c0 + ext))).astype(np.float32)
        transform = src.transform * Affine.translation(c0, r0)
        crs = src.crs.to_wkt()
    work = tmp_path_factory.mktemp("relief")
    scenes, paths, ortho_path, dem_path = line_scanner_block(work, ortho, transform, crs, relief=300.0, size=SIZE)
    return scenes, paths, ortho_path, dem_path, transform


def _figures(ds, store, scenes, transform):
    own, seam = mosaic_errors(ds, [s.to_ortho for s in scenes], [(SIZE, SIZE)] * len(scenes), transform,
                              positions=scene_positions(ds, store))
    valid = np.isfinite(own)
    return float(np.sqrt(np.mean(own[valid] ** 2))), float(own[valid].max()), float(np.sqrt(np.mean(seam**2))), valid.mean()


@pytest.mark.cluster
def test_line_scanner_with_dem_beats_polynomial_over_relief(relief_block, client, tmp_path):
    scenes, paths, ortho_path, dem_path, transform = relief_block
    out = tmp_path / "ls.zarr"
    ds = mosaic(paths, reference=ortho_path, out=out, tile=128, client=client, model="linescanner", dem=dem_path,
                report=tmp_path / "report")
    s = json.loads(ds.attrs["summary"])
    assert s["left_out"] == {} and len(json.loads(ds.attrs["scenes"])) == 4
    assert [json.loads(ds.attrs["models"])[k]["kind"] for k in range(4)] == ["linescanner"] * 4
    rmse, mx, seam, valid = _figures(ds, out, scenes, transform)
    # the height layer is the DEM at every covered pixel's centre
    h = ds.height.values
    assert np.isfinite(h[ds.source.values != 65535]).all() and 0 <= np.nanmin(h) and np.nanmax(h) <= 300.0 + 1e-3
    assert (tmp_path / "report" / "report.md").is_file() and (tmp_path / "report" / "overlap_graph.png").is_file()

    # the same block and points, a polynomial per scene (in memory)
    poly = mosaic(paths, reference=ortho_path, tile=128, client=client, model="polynomial", dem=dem_path)
    assert [m["kind"] for m in json.loads(poly.attrs["models"])] == ["polynomial"] * 4
    p_rmse, p_max, p_seam, _ = _figures(poly, tmp_path / "none", scenes, transform)
    print(f"linescanner: rmse {rmse:.3f} max {mx:.3f} seam {seam:.3f}; polynomial: rmse {p_rmse:.3f} max {p_max:.3f} "
          f"seam {p_seam:.3f}")
    assert valid > 0.6
    assert rmse < 0.15 and mx < 0.5, (rmse, mx)
    assert seam < 0.2, seam
    # the same points, a polynomial per scene: the relief displacement is not in its model
    assert p_rmse > 0.6 and p_max > 2.0 and p_seam > 1.0, (p_rmse, p_max, p_seam)
    assert rmse < p_rmse / 5


def test_models_round_trip_and_window_projection(relief_block):
    """The stored models project as the live ones; the node-grid projection of a window
    agrees with the exact one to 0.01 px."""
    scenes, paths, _, _, transform = relief_block
    crs = scenes[0].crs_wkt
    ys, xs = np.mgrid[100:228, 140:268].astype(np.float64)
    e, n = transform * (xs + 0.5, ys + 0.5)
    h = np.random.default_rng(0).uniform(0.0, 300.0, e.shape)
    ground = np.column_stack([e.ravel(), n.ravel(), h.ravel()])
    for kind in ("linescanner", "rpc"):
        model = sensor_model(kind, scene_sensor(paths[0], kind), crs)
        params = model.initial_params() + 1e-3
        again, p2 = model_from_dict(json.loads(json.dumps(model_to_dict(model, params))))
        exact = model.project(params, ground)
        np.testing.assert_allclose(again.project(p2, ground), exact, atol=1e-9)
        x, y = project_window(model, params, e, n, h)
        assert np.all(np.isfinite(exact))
        assert float(np.max(np.hypot(x.ravel() - exact[:, 0], y.ravel() - exact[:, 1]))) < 0.01
        # the navigation as delivered is off by a pixel or a few (what the adjustment corrects)
        on_dem = np.column_stack([e.ravel(), n.ravel(), scenes[0].terrain(e.ravel(), n.ravel())])
        truth = scenes[0].to_ortho(*model.project(model.initial_params(), on_dem).T)
        off = np.hypot(truth[0] - xs.ravel(), truth[1] - ys.ravel())
        assert 0.3 < float(np.median(off)) < 10.0, float(np.median(off))


def test_model_needs_what_the_scene_carries(relief_block, tmp_path):
    from geocoder.scene import write_geotiff

    scenes, paths, ortho_path, dem_path, _ = relief_block
    bare = tmp_path / "bare.tif"
    write_geotiff(bare, scenes[0].image)
    for kind, what in (("linescanner", "line-scanner model"), ("rpc", "RPC")):
        with pytest.raises(InputError, match=f"bare.tif.*{what}"):
            mosaic([paths[1], bare], reference=ortho_path, model=kind)
    with pytest.raises(ValueError, match="model must be one of"):
        mosaic(paths, reference=ortho_path, model="frame")
    # the command line passes --model and --dem through, and names the scene before starting any work
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "geocoder.cli", "mosaic", str(paths[1]), str(bare), "--reference", str(ortho_path),
                        "--out", str(tmp_path / "m.zarr"), "--model", "rpc", "--dem", str(dem_path)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and "bare.tif" in r.stderr and "carries no RPC metadata" in r.stderr, r.stderr
    assert not (tmp_path / "m.zarr").exists()
