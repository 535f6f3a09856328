"""Scenes the reference cannot find, placed through their neighbours (:mod:`geocoder.mosaic.placement`).

Truth as in ``tests/test_mosaic.py``: every scene is a synthetic ortho seen through a known
mapping (:mod:`geocoder.simulate.block`: rotation, scale, a quadratic term, new gain and
noise); the reference is that ortho made constant where a scene must not be found on it, so
that scene has no control and only its neighbours can place it.

- A 2 x 2 block (40 % overlap) whose reference is blank over scene 3: scene 3 is placed
  through a neighbour and carried by its tie points with all three of them.
- A strip of three whose reference is blank right of scene 0's first 55 %: scene 1 is placed
  through scene 0 in the first round, scene 2 (which overlaps scene 1 only) through scene 1
  in the second: a chain.
- Without a cluster: a scene's georeference or RPC prior picks the placed scenes it is matched with.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from affine import Affine

from geocoder.mosaic import mosaic
from geocoder.quality.accuracy import mosaic_errors
from geocoder.scene import write_geotiff
from geocoder.simulate.block import BlockScene, render
from geocoder.simulate.texture import synthetic_ortho

ORTHO = Affine(2.0, 0.0, 500000.0, 0.0, -2.0, 5800000.0)
SIZE = 256
STEP = int(SIZE * 0.6)  # 40 % overlap
BLOCK_SHAPE = (32 + STEP + SIZE + 32,) * 2
STRIP_SHAPE = (384, 64 + 2 * STEP + SIZE + 64)


def _scene(k: int, row0: float, col0: float, angle: float, scale: float, quadratic: float) -> BlockScene:
    return BlockScene(row0=row0, col0=col0, size=SIZE, angle_deg=angle, scale=scale, quadratic_px=quadratic,
                      gain=1.0 + 0.1 * k, offset=2.0 * k)


BLOCK = [_scene(k, 32 + r * STEP, 32 + c * STEP, a, s, q) for k, ((r, c), a, s, q) in enumerate(
    zip([(0, 0), (0, 1), (1, 0), (1, 1)], [2.0, -3.0, 1.5, -1.0], [1.0, 1.02, 0.98, 1.01], [1.5, -2.0, 1.0, 2.0]))]
STRIP = [_scene(k, 64, 64 + k * STEP, a, s, q) for k, (a, s, q) in enumerate([(1.5, 1.0, 1.0), (-2.0, 1.02, -1.5),
                                                                            (1.0, 0.99, 1.2)])]


def _files(d, scenes: list[BlockScene], shape: tuple[int, int], blank: tuple[slice, slice], seed: int) -> list:
    ortho = np.squeeze(synthetic_ortho(shape, seed=seed)).astype(np.float32)
    reference = ortho.copy()
    reference[blank] = float(ortho.mean())
    write_geotiff(d / "ortho.tif", reference, transform=ORTHO, crs="EPSG:32633")
    paths = []
    for k, scene in enumerate(scenes):
        paths.append(d / f"scene{k}.tif")
        write_geotiff(paths[-1], render(ortho, scene, seed=k))  # no georeference
    return paths


def _figures(ds, scenes: list[BlockScene]) -> tuple[list[tuple[float, float, int]], float]:
    """Per scene, RMSE and max of the mosaic's error (output px) over the pixels taken from it and
    their count; the RMS disagreement of the scenes wherever two overlap."""
    own, seam = mosaic_errors(ds, [s.to_ortho for s in scenes], [(SIZE, SIZE)] * len(scenes), ORTHO)
    source = ds.source.values
    out = []
    for k in range(len(scenes)):
        mine = own[source == k]
        assert np.isfinite(mine).all()
        out.append((float(np.sqrt(np.mean(mine**2))), float(mine.max()), int(mine.size)))
    return out, float(np.sqrt(np.mean(seam**2)))


@pytest.mark.cluster
def test_a_scene_blank_on_the_reference_is_placed_through_its_neighbours(client, tmp_path):
    # blank over scene 3's footprint (and a margin for its rotation): scenes 1 and 2 keep the
    # rest of theirs, scene 0 all but a corner
    paths = _files(tmp_path, BLOCK, BLOCK_SHAPE, (slice(32 + STEP - 8, None), slice(32 + STEP - 8, None)), seed=21)
    ds = mosaic(paths, reference=tmp_path / "ortho.tif", tile=128, client=client)
    s = json.loads(ds.attrs["summary"])
    # without the neighbour pass scene 3 would have been left out: the reference does not find it
    assert s["placed"]["3"] in ("via scene 1", "via scene 2")
    assert [s["placed"][str(k)] for k in range(3)] == ["reference"] * 3
    assert s["control_points"][3] == 0 and s["left_out"] == {} and s["block"] == [0, 1, 2, 3]
    assert {(1, 3), (2, 3)} <= {(p["i"], p["j"]) for p in s["pairs"] if p["ties"]}
    figures, seam = _figures(ds, BLOCK)
    print("2 x 2, per scene (rmse, max, pixels):", figures, "seam rms:", seam)
    # scene 3 is held by ties along two of its sides only: its far corner is extrapolated
    rmse, worst, n = figures[3]
    assert n > 0.3 * SIZE**2 and rmse < 0.2 and worst < 0.7
    assert all(f[0] < 0.1 for f in figures[:3]) and seam < 0.1


@pytest.mark.cluster
def test_a_chain_of_scenes_missing_from_the_reference(client, tmp_path):
    paths = _files(tmp_path, STRIP, STRIP_SHAPE, (slice(None), slice(64 + int(SIZE * 0.55), None)), seed=31)
    write_geotiff(tmp_path / "flat.tif", np.full((128, 128), 50.0, dtype=np.float32))  # found nowhere
    ds = mosaic([*paths, tmp_path / "flat.tif"], reference=tmp_path / "ortho.tif", tile=128, client=client)
    s = json.loads(ds.attrs["summary"])
    assert s["placed"] == {"0": "reference", "1": "via scene 0", "2": "via scene 1", "3": "not placed"}
    assert s["control_points"][0] > 0 and s["control_points"][1:] == [0, 0, 0]
    assert list(s["left_out"]) == ["3"] and s["left_out"]["3"].startswith("not found on the reference")
    assert "nor on a placed scene (too little texture to match it" in s["left_out"]["3"]
    assert s["block"] == [0, 1, 2] and {(p["i"], p["j"]) for p in s["pairs"] if p["ties"]} == {(0, 1), (1, 2)}
    figures, seam = _figures(ds, STRIP)
    print("strip, per scene (rmse, max, pixels):", figures, "seam rms:", seam)
    # scene 2 hangs on scene 1's ties, scene 1 on scene 0's, scene 0 has control on half of it:
    # the error grows along the chain
    assert figures[0][0] < 0.05 and figures[1][0] < 0.15 and figures[2][0] < 0.4 and figures[2][1] < 0.8
    assert seam < 0.1
    # nothing of scene 2 is cut off (its footprint is its adjusted model's, not the overlap's extrapolation)
    assert (ds.source.values != 65535).sum() > 0.98 * (SIZE * SIZE + 2 * SIZE * STEP)


def test_a_prior_picks_the_neighbours_and_predicts_the_pair():
    """A scene that carries a georeference or RPCs is matched only with the placed scenes its
    prior says it overlaps, each pair started from the prior chained through the neighbour."""
    from geocoder.kernels.polynomial import PolyMap
    from geocoder.mosaic.placement import _candidates

    shapes = [(200, 200)] * 4
    offsets = {0: (0.0, 0.0), 1: (150.0, 0.0), 2: (1000.0, 0.0)}  # scene k pixel + offset = reference pixel
    to_ref = {k: PolyMap.from_affine(np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]])) for k, (dx, dy) in offsets.items()}
    ref_to = {k: PolyMap.from_affine(np.array([[1.0, 0.0, -dx], [0.0, 1.0, -dy]])) for k, (dx, dy) in offsets.items()}
    prior = np.array([[1.0, 0.0, -280.0], [0.0, 1.0, -20.0]])  # scene 3 at (280, 20): overlaps scene 1 only
    near = _candidates(3, [0, 1, 2], set(), shapes, to_ref, ref_to, prior)
    assert [j for j, _ in near] == [1]
    np.testing.assert_allclose(near[0][1], [[1.0, 0.0, -130.0], [0.0, 1.0, -20.0]], atol=1e-9)  # scene 1 px -> scene 3 px
    assert _candidates(3, [0, 1, 2], {1}, shapes, to_ref, ref_to, prior) == []  # tried already
    assert [j for j, p in _candidates(3, [0, 1, 2], set(), shapes, to_ref, ref_to, None)] == [0, 1, 2]  # blind: all
