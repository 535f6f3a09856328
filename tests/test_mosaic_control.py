"""``mosaic(control=CSV)``: ground control points given by hand; ``resolution=``, ``crs=``: another output grid.

The 2 x 2 block of ``test_mosaic`` (its fixture and truth). The CSV's points are the
simulator's truth: scene pixel -> ortho pixel (``BlockScene.to_ortho``) -> map coordinates of
the reference, so a mosaic controlled by them alone must be placed as accurately as one
controlled by the reference's matches (``test_block_mosaic_against_truth``: < 0.1 px RMSE).
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from test_mosaic import ORTHO, SCENES, SIZE, block, errors  # noqa: F401 (the module's fixture: the block's files)

from geocoder.errors import GeocoderError, InputError
from geocoder.geometry import pixel_to_world
from geocoder.mosaic import MosaicSummary, mosaic

pytestmark = pytest.mark.cluster

#: Points per scene: its four corners 40 px inside, and its centre; every scene's sixth, withheld as a check.
PIXELS = [(40, 40), (280, 40), (40, 280), (280, 280), (160, 160), (100, 200)]


@pytest.fixture(scope="module")
def files(block):  # noqa: F811
    """The block's reference and its four scenes (``test_mosaic``'s)."""
    return block


def write_csv(path, rows: list[list], header: str = "id,scene,col,row,x,y") -> None:
    path.write_text(header + "\n" + "".join(",".join(str(v) for v in r) + "\n" for r in rows))


def truth_rows(scenes=range(4), by_name: bool = False) -> list[list]:
    """``id, scene, col, row, x, y`` of :data:`PIXELS` in every scene, from the simulator's truth."""
    rows = []
    for k in scenes:
        col, row = np.array(PIXELS, dtype=np.float64).T
        x, y = pixel_to_world(ORTHO, *SCENES[k].to_ortho(col, row))
        for n in range(len(col)):
            rows.append([f"p{k}{n}", f"scene{k}.tif" if by_name else k, col[n], row[n], f"{x[n]:.4f}", f"{y[n]:.4f}"])
    return rows


def test_csv_control_alone_places_the_block(files, client, tmp_path):
    """No reference match is control (``control_scenes=[]``): 5 points per scene from the CSV
    (and a sixth withheld as a check point) place the mosaic as the reference's matches do."""
    d, paths = files
    csv = tmp_path / "gcp.csv"
    write_csv(csv, truth_rows(by_name=True))
    ds = mosaic(paths, reference=d / "ortho.tif", tile=128, client=client, control_scenes=[], control=csv,
                check_points=1 / 6)
    s = json.loads(ds.attrs["summary"])
    print("given", s["given_points"], s["given_rmse_px"], "check", s["check_points"], s["check_rmse_px"])
    assert s["left_out"] == {} and s["control_points"] == [0, 0, 0, 0]
    assert s["given_file"] == str(csv) and s["given_points"] == [5, 5, 5, 5] and s["check_points"] == [1, 1, 1, 1]
    assert all(r < 0.1 for r in s["given_rmse_px"]) and all(r < 0.1 for r in s["check_rmse_px"])
    assert any(line.startswith(f"control points from {csv}: 20 used") for line in MosaicSummary(**s).lines())
    # every CSV point by its id: the used ones' residuals are the per-scene RMS's, the withheld ones the checks'
    by_id = {pid: (k, r, role) for pid, k, r, role in s["given_residuals"]}
    assert sorted(by_id) == sorted(row[0] for row in truth_rows())
    for k in range(4):
        used = [r for pid, (kk, r, role) in by_id.items() if kk == k and role == "control"]
        check = [r for pid, (kk, r, role) in by_id.items() if kk == k and role == "check"]
        assert len(used) == 5 and len(check) == 1
        assert np.sqrt(np.mean(np.square(used))) == pytest.approx(s["given_rmse_px"][k], abs=2e-4)
        assert check[0] == pytest.approx(s["check_rmse_px"][k], abs=2e-4)
    own, seam = errors(ds)
    rmse = float(np.sqrt(np.nanmean(own**2)))
    print("RMSE against truth (output px)", rmse, "max", np.nanmax(own), "seam", float(np.sqrt(np.mean(seam**2))))
    assert rmse < 0.1, rmse  # the reference-controlled block's bound (test_mosaic)
    assert float(np.sqrt(np.mean(seam**2))) < 0.2
    # the report lists them
    from geocoder.mosaic import write_report

    write_report(ds, tmp_path / "report")
    md = (tmp_path / "report" / "report.md").read_text()
    assert "| id | scene | residual px | role |" in md
    assert all(f"| {pid} | {k} |" in md for pid, (k, _, _) in by_id.items()) and md.count("| check |") == 4


@pytest.mark.parametrize("header, rows, message", [
    ("scene,col,row,x", [[0, 10, 10, 500300.0]], "line 1: missing column(s) y"),
    ("scene,col,row,x,y", [[0, 10, 10, 500300.0, 5799700.0], [1, "ten", 10, 500300.0, 5799700.0]],
     "line 3, column 'col': 'ten' is not a finite number"),
    ("scene,col,row,x,y", [[7, 10, 10, 500300.0, 5799700.0]], "line 2, column 'scene': '7' is not a scene"),
    ("scene,col,row,x,y", [["nowhere.tif", 10, 10, 500300.0, 5799700.0]], "line 2, column 'scene': 'nowhere.tif'"),
    ("scene,col,row,x,y", [[2, 10, 400, 500300.0, 5799700.0]], "line 2, columns 'col', 'row': (10, 400) is outside scene 2"),
    ("scene,col,row,x,y,sigma", [[0, 10, 10, 500300.0, 5799700.0, -1]], "line 2, column 'sigma': -1 is not positive"),
])
def test_malformed_csv_names_file_line_and_column(files, tmp_path, header, rows, message):
    d, paths = files
    csv = tmp_path / "bad.csv"
    write_csv(csv, rows, header)
    with pytest.raises(InputError) as e:
        mosaic(paths, reference=d / "ortho.tif", tile=128, control=csv)  # refused before any work
    assert str(e.value).startswith(f"{csv}: ") and message in str(e.value), str(e.value)


def test_cli_malformed_csv_exits_2_without_traceback(files, tmp_path):
    d, paths = files
    csv = tmp_path / "bad.csv"
    write_csv(csv, [[0, 10, 10, "east", 5799700.0]], "scene,col,row,x,y")
    r = subprocess.run([sys.executable, "-m", "geocoder.cli", "-q", "mosaic", *map(str, paths), "--reference",
                        str(d / "ortho.tif"), "--out", str(tmp_path / "m.zarr"), "--control", str(csv)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert f"{csv}: line 2, column 'x': 'east' is not a finite number" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "m.zarr").exists()
    r = subprocess.run([sys.executable, "-m", "geocoder.cli", "-q", "mosaic", *map(str, paths), "--reference",
                        str(d / "ortho.tif"), "--out", str(tmp_path / "m.zarr"), "--crs", "EPSG:999999"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "'EPSG:999999' is not a coordinate reference system" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


def test_output_over_the_csv_is_refused(files, tmp_path):
    d, paths = files
    csv = tmp_path / "gcp.csv"
    write_csv(csv, truth_rows())
    with pytest.raises(GeocoderError, match="is also an input of this job"):
        mosaic(paths, reference=d / "ortho.tif", out=csv, control=csv, overwrite=True)
    assert csv.read_text().startswith("id,scene,col,row,x,y")


def test_grid_options_refused_where_they_cannot_work(files):
    d, paths = files
    with pytest.raises(ValueError, match="resolution must be a positive number"):
        mosaic(paths, reference=d / "ortho.tif", resolution=0.0)
    with pytest.raises(InputError, match="is not georeferenced"):  # a scene without georeference as the reference
        mosaic(paths[1:], reference=paths[0], crs="EPSG:3857")


@pytest.fixture(scope="module")
def default_pair(files, client):
    """Scenes 0 and 1 on the reference's grid (today's output): what the other grids are compared with."""
    d, paths = files
    return mosaic(paths[:2], reference=d / "ortho.tif", tile=128, client=client)


def truth_error(ds) -> np.ndarray:
    """Per covered output pixel, its distance (output pixels) from where the simulator's truth puts
    the scene position the mosaic sampled there (through the output's CRS); NaN elsewhere."""
    from pyproj import Transformer

    from geocoder.geometry import world_to_pixel
    from geocoder.mosaic import scene_positions

    scenes = [SCENES[int(s.rsplit("scene", 1)[1][0])] for s in json.loads(ds.attrs["scenes"])]
    to_out = Transformer.from_crs("EPSG:32633", ds.rio.crs, always_xy=True)
    src = ds.source.values
    rows, cols = np.indices(src.shape)
    err = np.full(src.shape, np.nan)
    for n, ((x, y), scene) in enumerate(zip(scene_positions(ds, "unused: no dense fields"), scenes)):
        sel = src == n
        c, r = world_to_pixel(ds.rio.transform(), *to_out.transform(*pixel_to_world(ORTHO, *scene.to_ortho(x[sel], y[sel]))))
        err[sel] = np.hypot(c - cols[sel], r - rows[sel])
    return err


def grey_difference(ds, default) -> np.ndarray:
    """``ds``'s mosaic minus ``default``'s interpolated (bilinear) at the same ground points, where both have data."""
    from pyproj import Transformer
    from scipy.ndimage import map_coordinates

    from geocoder.geometry import world_to_pixel

    e, n = np.meshgrid(ds.x.values, ds.y.values)
    e, n = Transformer.from_crs(ds.rio.crs, default.rio.crs, always_xy=True).transform(e, n)
    c, r = world_to_pixel(default.rio.transform(), e, n)
    v = map_coordinates(default.mosaic.values[0], [r, c], order=1, cval=np.nan)
    d = ds.mosaic.values[0] - v
    return d[np.isfinite(d)]


def test_resolution_twice_the_reference_pixel(files, client, default_pair):
    d, paths = files
    ds = mosaic(paths[:2], reference=d / "ortho.tif", tile=128, client=client, resolution=4.0)
    t = ds.rio.transform()
    assert (t.a, t.e) == (4.0, -4.0) and t.c % 4 == 0 and t.f % 4 == 0 and ds.rio.crs == default_pair.rio.crs
    assert all(abs(2 * a - b) <= 2 for a, b in zip(ds.mosaic.shape[1:], default_pair.mosaic.shape[1:]))
    err = truth_error(ds)
    rmse = float(np.sqrt(np.nanmean(err**2)))
    diff = grey_difference(ds, default_pair)
    std = float(np.nanstd(default_pair.mosaic.values))
    print("default grid: RMSE against truth (output px)", float(np.sqrt(np.nanmean(truth_error(default_pair) ** 2))))
    print("resolution 4 m: RMSE against truth (output px)", rmse, "grey difference RMS / std", np.sqrt(np.mean(diff**2)) / std,
          "pixels", diff.size)
    assert np.isfinite(err).mean() > 0.5 and rmse < 0.03  # measured 0.005 (4 m), 0.010 (zone 34); the default grid's 0.01
    assert diff.size > 0.5 * ds.mosaic.shape[1] * ds.mosaic.shape[2]
    assert np.sqrt(np.mean(diff**2)) < 0.08 * std  # measured 0.039 (4 m), 0.029 (zone 34): interpolated twice


def test_crs_utm_zone_next_door(files, client, default_pair, tmp_path):
    import rasterio
    import rioxarray  # noqa: F401 (the .rio accessor)
    import xarray as xr

    d, paths = files
    out, cog = tmp_path / "m34.zarr", tmp_path / "m34.tif"
    mosaic(paths[:2], reference=d / "ortho.tif", out=out, tile=128, client=client, crs="EPSG:32634", cog=cog)
    ds = xr.open_zarr(out, decode_coords="all", consolidated=False)
    assert ds.rio.crs.to_epsg() == 32634 and "models_crs" in ds.attrs
    with rasterio.open(cog) as f:
        assert f.crs.to_epsg() == 32634 and f.transform == ds.rio.transform()
    # the reference's 2 m pixel measured in zone 34, 6 degrees of longitude west of its meridian (scale 1.002)
    from pyproj import Proj, Transformer

    lon, lat = Transformer.from_crs("EPSG:32633", "EPSG:4326", always_xy=True).transform(500768.0, 5799232.0)
    k33, k34 = (Proj(f"EPSG:{z}").get_factors(lon, lat).areal_scale for z in (32633, 32634))
    assert abs(ds.rio.transform().a - 2.0 * np.sqrt(k34 / k33)) < 1e-4, (ds.rio.transform().a, k33, k34)
    err = truth_error(ds)
    rmse = float(np.sqrt(np.nanmean(err**2)))
    diff = grey_difference(ds, default_pair)
    std = float(np.nanstd(default_pair.mosaic.values))
    print("EPSG:32634: RMSE against truth (output px)", rmse, "grey difference RMS / std", np.sqrt(np.mean(diff**2)) / std,
          "pixels", diff.size)
    assert np.isfinite(err).mean() > 0.5 and rmse < 0.03  # measured 0.005 (4 m), 0.010 (zone 34); the default grid's 0.01
    assert diff.size > 0.5 * ds.mosaic.shape[1] * ds.mosaic.shape[2]
    assert np.sqrt(np.mean(diff**2)) < 0.08 * std  # measured 0.039 (4 m), 0.029 (zone 34): interpolated twice


def test_changed_csv_is_not_resumed(files, client, tmp_path):
    """A job killed part-way with one CSV, re-run with the CSV edited in place (same size): the job
    key holds the file's digest, so nothing of the killed job is reused."""
    from test_mosaic_resume import TILE, run_and_kill

    d, paths = files
    csv = tmp_path / "gcp.csv"
    rows = truth_rows(scenes=(0, 1))
    write_csv(csv, rows)
    args = [*paths[:2], "--reference", d / "ortho.tif", "--tile", TILE, "--control", csv, "--scheduler", client.scheduler.address]
    first = run_and_kill(args, tmp_path, "tiles/*/*.pkl")
    rows[0][4] = rows[0][4][:-1] + ("1" if rows[0][4][-1] != "1" else "2")  # 0.1 mm east: same size, other content
    write_csv(csv, rows)
    ds = mosaic(paths[:2], reference=d / "ortho.tif", out=tmp_path / "m.zarr", tile=TILE, client=client, control=csv,
                overwrite=first.returncode == 0)
    s = json.loads(ds.attrs["summary"])
    assert not s["job"]["resumed"] and s["job"]["skipped"] == 0 and s["given_points"] == [6, 6]
