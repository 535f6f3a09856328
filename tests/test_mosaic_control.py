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

from geocoder.errors import InputError
from geocoder.geometry import pixel_to_world
from geocoder.mosaic import mosaic

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
    own, seam = errors(ds)
    rmse = float(np.sqrt(np.nanmean(own**2)))
    print("RMSE against truth (output px)", rmse, "max", np.nanmax(own), "seam", float(np.sqrt(np.mean(seam**2))))
    assert rmse < 0.1, rmse  # the reference-controlled block's bound (test_mosaic)
    assert float(np.sqrt(np.mean(seam**2))) < 0.2


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
