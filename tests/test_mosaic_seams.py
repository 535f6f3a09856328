"""Least-cost seams of a mosaic: the coarse cut, the feathered label blend, and a real run against truth.

Kernel tests build coarse scenes whose best seam is known (a column of low cost, a bright
object on the centre rule's seam); the cluster test renders two overlapping scenes from an
orthoimage (:mod:`geocoder.simulate.block`, known mapping of every pixel) and gives one of
them a bright object, seen by it alone, right on the centre rule's seam.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from affine import Affine

from geocoder.mosaic.compose import NO_SOURCE
from geocoder.mosaic.seams import (
    CoarseScene,
    centre_labels,
    grid_min_cut,
    label_weights,
    least_cost_labels,
    seam_pairs,
    upsample_labels,
)


def test_grid_min_cut_takes_the_cheap_column():
    h, w = 6, 12
    cost = np.full((h, w), 5)
    cost[:, 6:8] = 1  # crossing between columns 6 and 7 costs 2, anywhere else 10
    active = np.zeros((h, w), bool)
    active[:, 2:10] = True
    source, sink = np.zeros_like(active), np.zeros_like(active)
    source[:, 1], sink[:, 10] = True, True
    side = grid_min_cut(cost, active, source, sink)
    expected = np.zeros_like(active)
    expected[:, 2:7] = True
    np.testing.assert_array_equal(side, expected)


def _pair(object_in_first: bool, seed: int = 0):
    """Two coarse scenes side by side (cells 0-39 and 20-59), overlapping in cells 20-39."""
    rng = np.random.default_rng(seed)
    h = 40
    ground = rng.normal(100.0, 5.0, (h, 60)).astype(np.float32)
    vi = ground[:, :40] + rng.normal(0, 1, (h, 40)).astype(np.float32)
    vj = ground[:, 20:] + rng.normal(0, 1, (h, 40)).astype(np.float32)
    if object_in_first:
        vi[15:25, 27:33] += 80.0  # on the centre rule's seam (column 30), seen by the first scene only

    def scene(col0, v):
        yy, xx = np.mgrid[0:h, 0:40]
        score = np.maximum(np.abs(xx - 19.5) / 19.5, np.abs(yy - 19.5) / 19.5)
        return CoarseScene(0, col0, v, score, np.ones(v.shape, bool))

    return [scene(0, vi), scene(20, vj)]


def test_least_cost_seam_goes_around_an_object_and_stays_near_the_centre_elsewhere():
    scenes = _pair(True)
    centre = centre_labels((40, 60), scenes)
    cut = least_cost_labels((40, 60), scenes, [(0, 1)], width=8)
    obj = (slice(15, 25), slice(27, 33))
    # the centre rule splits the object between the scenes; the cut leaves it whole in one
    assert 0 < np.count_nonzero(centre[obj] == 0) < centre[obj].size
    labels = np.unique(cut[obj])
    assert labels.size == 1
    # every row is still one run of scene 0 then one of scene 1, the seam within the corridor
    for row in cut:
        switch = np.flatnonzero(np.diff(row.astype(int)))
        assert switch.size == 1 and 22 <= switch[0] <= 38
    # without the object, the cut keeps to the centre rule's straight seam within a few cells
    # (rows 10-29: nearer the top and bottom the toy scores' Chebyshev corners bend it, and a cut straightens that)
    plain = least_cost_labels((40, 60), _pair(False), [(0, 1)], width=8)
    cols = (plain == 0).sum(axis=1)[10:30]
    assert np.all(np.abs(cols - (centre == 0).sum(axis=1)[10:30]) <= 4)
    # only cells both scenes cover change hands
    assert np.all(cut[:, :20] == 0) and np.all(cut[:, 40:] == 1)


def test_label_weights_ramp_linearly_across_the_boundary():
    label = np.zeros((4, 20), np.uint16)
    label[:, 10:] = 1
    label[:, 18:] = NO_SOURCE  # no label: it does not count as a boundary
    w = label_weights(label, np.array([0, 1]), feather=6.0)
    # pixel 9 is 1/2 px inside scene 0's side of the boundary, pixel 10 1/2 px inside scene 1's
    t = np.arange(20) - 9.5  # signed distance on scene 1's side
    expected1 = np.clip(0.5 + t / 6.0, 0, 1)
    np.testing.assert_allclose(w[1, 0, :18], expected1[:18], atol=1e-6)
    np.testing.assert_allclose(w[0, 0, :18], 1 - expected1[:18], atol=1e-6)
    assert np.all(w[:, :, 18:] == 0)
    hard = label_weights(label, np.array([0, 1]), feather=0.0)
    np.testing.assert_array_equal(hard[1, 0, :18], (np.arange(18) >= 10).astype(np.float32))


def test_upsampled_labels_and_seam_pixels():
    coarse = np.array([[0, 1], [2, 1]], np.uint16)
    up = upsample_labels(coarse, 0, 0, (-1, 5, 0, 4), 2, (4, 3))
    assert up.shape == (6, 4)
    np.testing.assert_array_equal(up[1], [0, 0, 1, NO_SOURCE])  # column 3 and row -1 lie outside the 4 x 3 mosaic
    assert np.all(up[0] == NO_SOURCE)
    r, c, a, b = seam_pairs(up[1:5, :3])
    pairs = {(int(x), int(y), int(p), int(q)) for x, y, p, q in zip(r, c, a, b)}
    assert pairs == {(0, 1, 0, 1), (1, 1, 0, 1), (1, 0, 0, 2), (1, 1, 0, 2), (2, 1, 2, 1), (3, 1, 2, 1)}
    assert r.size == 6  # pixel (1, 1) twice: its right and its lower neighbour


# ---------------------------------------------------------------------------- on a cluster
ORTHO = Affine(2.0, 0.0, 500000.0, 0.0, -2.0, 5800000.0)
SIZE = 256


@pytest.fixture(scope="module")
def pair_with_object(tmp_path_factory):
    from geocoder.scene import write_geotiff
    from geocoder.simulate.block import BlockScene, render
    from geocoder.simulate.texture import synthetic_ortho

    d = tmp_path_factory.mktemp("seams")
    ortho = np.squeeze(synthetic_ortho((640, 640), seed=21)).astype(np.float32)
    write_geotiff(d / "ortho.tif", ortho, transform=ORTHO, crs="EPSG:32633")
    scenes = [BlockScene(row0=100, col0=c0, size=SIZE, angle_deg=a, scale=1.0, quadratic_px=q, gain=1.0 + 0.1 * k,
                         offset=2.0 * k) for k, (c0, a, q) in enumerate([(100, 1.0, 1.0), (260, -1.5, -1.0)])]
    paths = []
    for k, s in enumerate(scenes):
        img = render(ortho, s, seed=k)
        if k == 0:  # the centre rule's seam runs near ortho column 308, scene 0's column ~208
            img[100:160, 196:222] += 3.0 * float(ortho.std())
        paths.append(d / f"scene{k}.tif")
        write_geotiff(paths[-1], img)
    return d, paths, scenes


@pytest.mark.cluster
def test_least_cost_seams_avoid_the_object_and_do_not_depend_on_the_tiling(pair_with_object, client):
    from geocoder.mosaic import load_models, mosaic
    from geocoder.mosaic.diagnostics import seam_errors
    from geocoder.quality.accuracy import mosaic_errors

    d, paths, scenes = pair_with_object
    runs = {}
    for mode, out_tile in (("centre", 128), ("least-cost", 128), ("least-cost", 80)):
        runs[mode, out_tile] = mosaic(paths, reference=d / "ortho.tif", tile=128, output_tile=out_tile, client=client,
                                      seams=mode)
    centre, cut, cut80 = runs["centre", 128], runs["least-cost", 128], runs["least-cost", 80]
    sc, sl = json.loads(centre.attrs["summary"]), json.loads(cut.attrs["summary"])
    assert sc["seam_mode"] == "centre" and sl["seam_mode"] == "least-cost" and sl["seam_cells_moved"] > 0
    # the object (+3 std, seen by one scene) sits on the centre seam: a large step there, none on the cut
    assert sc["seam_grey_step"] > 10 * sl["seam_grey_step"], (sc["seam_grey_step"], sl["seam_grey_step"])
    assert len(sl["seams"]) == 1 and sl["seams"][0]["pixels"] > SIZE  # one seam, top to bottom
    # the geometry is as good: error of every pixel and mismatch of the two scenes along the seam
    for ds in (centre, cut):
        own, _ = mosaic_errors(ds, [s.to_ortho for s in scenes], [(SIZE, SIZE)] * 2, ORTHO)
        assert float(np.sqrt(np.nanmean(own**2))) < 0.1
        mism = seam_errors(ds.source.values, ds.rio.transform(), load_models(ds), [s.to_ortho for s in scenes],
                           [(SIZE, SIZE)] * 2)
        assert mism.size > SIZE and float(np.sqrt(np.mean(mism**2))) < 0.2
    # another output tiling: the same mosaic (the seams are decided on the coarse grid)
    np.testing.assert_array_equal(cut.source.values, cut80.source.values)
    np.testing.assert_allclose(cut.mosaic.values, cut80.mosaic.values, atol=1e-3, equal_nan=True)
    assert json.loads(cut80.attrs["summary"])["seams"][0]["pixels"] == sl["seams"][0]["pixels"]
