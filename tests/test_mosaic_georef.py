"""``mosaic(scenes)`` without a reference orthoimage: the block placed and controlled by the scenes' georeferences.

The 2 x 2 block of ``test_mosaic`` (its truth), each scene written again with a north-up
georeference: the best north-up fit of its true scene pixel -> map mapping, then shifted by a
few pixels as a real one would be. The fit cannot hold the scenes' rotation (1-3 degrees),
scale change and bend, so the georeferences alone misplace pixels by up to several pixels and
disagree at the seams; the tie points must make the scenes agree with one another, and the
CSV control (``test_mosaic_control``'s points) must place the block as well as a reference does.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from affine import Affine
from test_mosaic import ORTHO, SCENES, SIZE, block, errors  # noqa: F401 (the module's fixture: the block's files)
from test_mosaic_control import truth_rows, write_csv

from geocoder.errors import InputError
from geocoder.geometry import pixel_to_world
from geocoder.mosaic import MosaicSummary, mosaic
from geocoder.scene import open_scene, write_geotiff

pytestmark = pytest.mark.cluster

#: Each georeference's error beyond the north-up fit (map pixels of the ortho, x and y).
SHIFTS = [(1.5, -1.0), (-1.0, 2.0), (0.5, 1.5), (-2.0, -0.5)]


def north_up(k: int) -> Affine:
    """The least-squares north-up transform of scene ``k``'s true mapping, shifted by ``SHIFTS[k]``."""
    c, r = (v.ravel() for v in np.meshgrid(np.linspace(0, SIZE - 1, 9), np.linspace(0, SIZE - 1, 9)))
    ex, ny = pixel_to_world(ORTHO, *SCENES[k].to_ortho(c, r))
    sx, x0 = np.polyfit(c + 0.5, ex, 1)
    sy, y0 = np.polyfit(r + 0.5, ny, 1)
    dx, dy = SHIFTS[k]
    return Affine(sx, 0.0, x0 + dx * ORTHO.a, 0.0, sy, y0 + dy * ORTHO.e)


@pytest.fixture(scope="module")
def georeferenced(block, tmp_path_factory):  # noqa: F811
    d, paths = block
    out = tmp_path_factory.mktemp("georef")
    geo = []
    for k, p in enumerate(paths):
        image = open_scene(p).values[0]
        geo.append(out / f"geo_scene{k}.tif")  # errors() reads the scene's index after "scene"
        write_geotiff(geo[-1], image, transform=north_up(k), crs="EPSG:32633")
    return out, geo


def georeference_errors(k: int) -> np.ndarray:
    """Error (ortho pixels) of scene ``k``'s georeference alone, on a grid of its pixels."""
    c, r = (v.ravel() for v in np.meshgrid(np.arange(0, SIZE, 8.0), np.arange(0, SIZE, 8.0)))
    gx, gy = ~ORTHO * (north_up(k) * (c + 0.5, r + 0.5))
    tx, ty = SCENES[k].to_ortho(c, r)
    return np.hypot(np.asarray(gx) - 0.5 - tx, np.asarray(gy) - 0.5 - ty)


def test_georeferences_alone_misplace_the_scenes():
    """The premise: each georeference alone is off by pixels (3.3-7.2 px RMS, 7-13 px at worst)."""
    rms = [float(np.sqrt(np.mean(georeference_errors(k) ** 2))) for k in range(4)]
    assert min(rms) > 3.0 and max(float(georeference_errors(k).max()) for k in range(4)) > 10.0, rms


def test_csv_control_without_reference(georeferenced, client, tmp_path):
    """No reference: placed by the georeferences, tied, controlled by the CSV as well as with a reference."""
    _, paths = georeferenced
    csv = tmp_path / "gcp.csv"
    write_csv(csv, truth_rows())
    ds = mosaic(paths, tile=128, client=client, control=csv, check_points=1 / 6)
    s = json.loads(ds.attrs["summary"])
    assert s["left_out"] == {} and len(s["pairs"]) == 6
    edges = {(0, 1), (0, 2), (1, 3), (2, 3)}  # the diagonal pairs overlap by 14-19 %, and may stay unmatched
    assert all(p["ties"] > 40 for p in s["pairs"] if (p["i"], p["j"]) in edges), s["pairs"]
    assert s["placed"] == {str(k): "georeference" for k in range(4)} and s["georeference_sigma_px"] is None
    assert s["given_points"] == [5, 5, 5, 5] and all(r < 0.1 for r in s["check_rmse_px"])
    assert ds.rio.crs.to_epsg() == 32633
    own, seam = errors(ds)
    rmse = float(np.sqrt(np.nanmean(own**2)))
    print("RMSE against truth (output px)", rmse, "max", np.nanmax(own), "seam", float(np.sqrt(np.mean(seam**2))))
    assert np.isfinite(own).mean() > 0.5
    assert rmse < 0.1, rmse  # the bound of the reference-controlled block (test_mosaic)
    assert float(np.sqrt(np.mean(seam**2))) < 0.2
    before, after = s["seam_step"]  # balanced among themselves: gains 1.10-1.25, offsets 0-9
    assert after < 0.2 * before


def test_georeferences_control_the_block(georeferenced, client, tmp_path):
    """No reference, no control: the scenes agree at the seams (ties) and land where their
    georeferences say on average (better than any one of them alone; default sigma 5 px)."""
    _, paths = georeferenced
    ds = mosaic(paths, tile=128, client=client, seams="centre", report=tmp_path / "report")
    assert "No reference orthoimage and no control points" in (tmp_path / "report" / "report.md").read_text()
    s = json.loads(ds.attrs["summary"])
    assert s["left_out"] == {} and s["control_points"] == [25] * 4 and s["georeference_sigma_px"] == 5.0
    assert any(line.startswith("no reference: the block is controlled by the scenes' georeferences")
               for line in MosaicSummary(**s).lines())
    own, seam = errors(ds)
    rmse = float(np.sqrt(np.nanmean(own**2)))
    print("RMSE against truth (output px)", rmse, "max", np.nanmax(own), "seam", float(np.sqrt(np.mean(seam**2))))
    assert float(np.sqrt(np.mean(seam**2))) < 0.2  # the ties make them agree, whatever the georeferences say
    # better than the best georeference alone: the block's common affine from all four; what is left
    # is their shifts' disagreement (up to 2 px), which four scenes cannot average away
    best = min(float(np.sqrt(np.mean(georeference_errors(k) ** 2))) for k in range(4))
    assert rmse < 0.6 * best, (rmse, best)


def test_scene_without_georeference_is_placed_by_its_neighbours(block, georeferenced, client, tmp_path):  # noqa: F811
    """Scene 3 raw (no georeference): matched against the georeferenced scenes it overlaps, then
    carried by its tie points; the CSV controls only scenes 0-2, so it has no control of its own."""
    _, raw = block
    _, paths = georeferenced
    csv = tmp_path / "gcp.csv"
    write_csv(csv, truth_rows(scenes=range(3)))
    ds = mosaic([*paths[:3], raw[3]], tile=128, client=client, control=csv)
    s = json.loads(ds.attrs["summary"])
    assert s["left_out"] == {} and s["placed"]["3"].startswith("via scene") and s["given_points"][3] == 0
    own, seam = errors(ds)
    rmse = float(np.sqrt(np.nanmean(own**2)))
    print("RMSE against truth (output px)", rmse, "max", np.nanmax(own), "seam", float(np.sqrt(np.mean(seam**2))))
    assert rmse < 0.1, rmse
    assert float(np.sqrt(np.mean(seam**2))) < 0.2


def test_without_reference_refusals(block, georeferenced):  # noqa: F811
    d, raw = block
    _, paths = georeferenced
    with pytest.raises(ValueError, match="dense refinement .* give reference"):
        mosaic(paths, tile=128, dense=True)
    with pytest.raises(ValueError, match="check points .* give control or reference"):
        mosaic(paths, tile=128, check_points=0.2)
    other = d / "utm34.tif"
    write_geotiff(other, open_scene(raw[1]).values[0], transform=north_up(1), crs="EPSG:32634")
    with pytest.raises(InputError, match=r"utm34\.tif.*another CRS"):
        mosaic([paths[0], other], tile=128)
    # the command line: --reference is optional; no georeferenced scene at all is refused in one line
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "geocoder.cli", "mosaic", str(raw[0]), str(raw[1]), "--out",
                        str(d / "never.zarr")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "scene0.tif" in r.stderr and "has no georeference" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and not (d / "never.zarr").exists()
