"""The mosaic report: Markdown tables and figures of the overlap graph, the adjustment and the seams.

A 2 x 2 block rendered from an orthoimage with known mappings (:mod:`geocoder.simulate.block`)
is mosaicked on a real cluster into a Zarr store with overview levels; the report is written
from the store and checked against what is known: four scenes in the block, six overlapping
pairs, sub-pixel agreement of the scenes, figures that show something.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest
from affine import Affine

from geocoder.errors import EnvironmentFailure, OutputError

ORTHO = Affine(2.0, 0.0, 500000.0, 0.0, -2.0, 5800000.0)
SIZE = 224
FIGURES = ["overlap_graph.png", "residuals.png", "seam_mismatch.png", "seams.png"]


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    from geocoder.scene import write_geotiff
    from geocoder.simulate.block import BlockScene, render
    from geocoder.simulate.texture import synthetic_ortho

    d = tmp_path_factory.mktemp("report")
    ortho = np.squeeze(synthetic_ortho((576, 576), seed=29)).astype(np.float32)
    write_geotiff(d / "ortho.tif", ortho, transform=ORTHO, crs="EPSG:32633")
    scenes = [BlockScene(row0=r0, col0=c0, size=SIZE, angle_deg=a, scale=1.0, quadratic_px=1.0, gain=1.0 + 0.05 * k,
                         offset=2.0 * k) for k, ((r0, c0), a) in enumerate(zip([(80, 80), (80, 230), (230, 80), (230, 230)],
                                                                                [1.0, -1.5, 2.0, -1.0]))]
    paths = []
    for k, s in enumerate(scenes):
        paths.append(d / f"scene{k}.tif")
        write_geotiff(paths[-1], render(ortho, s, seed=k))
    return d, paths


def _table(md: str, header: str) -> list[list[str]]:
    """The body rows of the Markdown table whose header row starts with ``header``."""
    lines = md.splitlines()
    start = next(n for n, line in enumerate(lines) if line.startswith(header))
    rows = []
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip("|").split("|")])
    return rows


@pytest.mark.cluster
def test_report_from_the_store(block, client, tmp_path):
    import matplotlib.image as mpimg

    from geocoder.mosaic import mosaic, write_report

    d, paths = block
    store = tmp_path / "m.zarr"
    ds = mosaic(paths, reference=d / "ortho.tif", out=store, tile=128, client=client)
    s = json.loads(ds.attrs["summary"])
    assert len(s["block"]) == 4 and len(s["pairs"]) == 6
    out = write_report(store, tmp_path / "report", max_size=200)
    assert sorted(p.name for p in (tmp_path / "report").iterdir()) == sorted([*FIGURES, "geocoder.json", "points.csv",
                                                                              "report.md"])
    md = (tmp_path / "report" / "report.md").read_text()
    # every adjusted ground point, as the store has them, and their precision summarised
    points = np.genfromtxt(tmp_path / "report" / "points.csv", delimiter=",", names=True)
    assert points.size == sum(int(v) for v in s["rays"].values()) and points.dtype.names[:3] == ("x", "y", "control")
    tie = points["control"] == 0
    median = float(_table(md, "| points | median |")[0][1])
    assert _table(md, "| points | median |")[0][0] == "tie" and median == pytest.approx(s["point_sigma_px"]["tie"][0], abs=1e-4)
    assert 0 < np.median(np.fmax(points["sigma_x"], points["sigma_y"])[tie]) < 0.05
    assert re.search(r"Observations left out: \d+ by the robust re-weighting, \d+ by data snooping", md)
    # drawn from an overview level (the mosaic is about 370 px; the 1:2 level is the coarsest >= 200 px), not the root
    assert "overview at 1:2" in md
    scenes = _table(md, "| scene | file |")
    assert len(scenes) == 4 and [r[1] for r in scenes] == [f"scene{k}.tif" for k in range(4)]
    rms = [float(r[4]) for r in scenes]
    np.testing.assert_allclose(rms, s["rms_px"], atol=1e-3)
    assert all(0 < v < 0.3 for v in rms)  # sub-pixel matching of scenes that agree by construction
    precision = [float(r[5]) for r in scenes]
    assert all(0 < v < 0.1 for v in precision)
    # the balance undoes the rendering's gains 1.00-1.15 (reference grey values are the truth)
    np.testing.assert_allclose([float(r[6]) for r in scenes], 1 / (1.0 + 0.05 * np.arange(4)), rtol=0.03)
    assert len(_table(md, "| pair | scene i |")) == 6
    seams = _table(md, "| pair | seam length px |")
    assert len(seams) == len(s["seams"]) >= 4  # the four side neighbours meet along seams (the diagonals may too)
    mismatch = np.array([float(r[4]) for r in seams if r[4] != "-"])
    assert mismatch.size >= 4 and np.all(mismatch < 0.2)
    assert re.search(r"Seamlines: least-cost", md)
    for name in FIGURES:
        img = mpimg.imread(tmp_path / "report" / name)
        assert img.shape[0] > 200 and img.shape[1] > 200 and float(img[..., :3].std()) > 0.05, name
    assert out == str(tmp_path / "report")
    # never over a directory geocoder did not write; over its own report only if asked
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    with pytest.raises(OutputError):
        write_report(store, tmp_path / "mine", overwrite=True)
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep"
    with pytest.raises(OutputError):
        write_report(store, tmp_path / "report")
    write_report(ds, tmp_path / "report", overwrite=True)  # the returned dataset works too
    assert (tmp_path / "report" / "report.md").read_text().count("\n| ") > 10
    assert not [p for p in tmp_path.iterdir() if ".partial-" in p.name or ".old-" in p.name]


@pytest.mark.cluster
def test_cli_mosaic_report(block, client, tmp_path):
    d, paths = block
    r = subprocess.run([sys.executable, "-m", "geocoder.cli", "-q", "mosaic", *map(str, paths), "--reference", str(d / "ortho.tif"),
                        "--out", str(tmp_path / "m.zarr"), "--tile", "128", "--seams", "centre", "--report",
                        str(tmp_path / "rep"), "--scheduler", client.scheduler.address],
                       capture_output=True, text=True, timeout=600, check=False)
    assert r.returncode == 0, r.stderr
    assert "seams (centre)" in r.stdout and "wrote the report" in r.stdout
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "Seamlines: centre" in md and len(_table(md, "| scene | file |")) == 4
    assert all((tmp_path / "rep" / f).stat().st_size > 1000 for f in FIGURES)


def test_missing_matplotlib_names_the_extra(monkeypatch):
    from geocoder.mosaic.report import require_matplotlib

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib raises ImportError
    with pytest.raises(EnvironmentFailure, match=r"geocoder\[report\]"):
        require_matplotlib()
