"""Dense refinement of the scenes without control, against their refined neighbours.

Two airborne strips side by side (60 % sidelap) with scan-line turbulence (up to 1.5 px,
changing over tens of lines), control on the first only: the block adjustment places the
second by tie points, but its model cannot follow the turbulence. With ``dense=True`` strip 0
is refined against the reference and strip 1 against strip 0 brought onto the reference grid;
each strip's own pixels in the mosaic (those it is the source of) are compared with the truth.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_mosaic import ORTHO, SIZE

from geocoder.mosaic import MosaicSummary, mosaic, scene_positions
from geocoder.mosaic.dense_neighbours import refinement_rounds
from geocoder.quality.accuracy import mosaic_errors
from geocoder.scene import write_geotiff
from geocoder.simulate.block import BlockScene, render
from geocoder.simulate.texture import synthetic_ortho
from geocoder.status import Status

pytestmark = pytest.mark.cluster

STRIPS = [BlockScene(row0=120, col0=c0, size=SIZE, angle_deg=a, scale=1.0, quadratic_px=q, gain=1.0 + 0.1 * k,
                     offset=2.0 * k, turbulence_px=1.5, turbulence_seed=k)
          for k, (c0, a, q) in enumerate([(96, 1.5, 1.0), (224, -2.0, -1.5)])]


def test_refinement_rounds_order():
    # a chain 0 - 1 - 2 - 3 (and 1 - 3); scene 4 tied to nothing; 0 refined against the reference
    rounds = refinement_rounds(5, {0}, {(0, 1): 50, (1, 2): 50, (2, 3): 50, (1, 3): 20})
    assert rounds == [[(1, [0])], [(2, [1])], [(3, [1, 2])]]
    assert refinement_rounds(3, {0, 1}, {(0, 2): 10, (1, 2): 10}) == [[(2, [0, 1])]]
    assert refinement_rounds(2, set(), {(0, 1): 10}) == []
    # strip 2 barely overlaps refined strip 0: it waits for strip 1, which it overlaps widely
    assert refinement_rounds(3, {0}, {(0, 1): 60, (1, 2): 70, (0, 2): 10}) == [[(1, [0])], [(2, [0, 1])]]
    # nothing qualifies (every open scene has a better unrefined neighbour): the best tied goes first
    assert refinement_rounds(3, {0}, {(0, 1): 30, (0, 2): 20, (1, 2): 70}) == [[(1, [0])], [(2, [0, 1])]]


def test_strips_without_control_follow_their_turbulence_via_neighbours(client, tmp_path):
    ortho = np.squeeze(synthetic_ortho((640, 640), seed=23)).astype(np.float32)
    write_geotiff(tmp_path / "ortho.tif", ortho, transform=ORTHO, crs="EPSG:32633")
    paths = []
    for k, scene in enumerate(STRIPS):
        paths.append(tmp_path / f"strip{k}.tif")
        write_geotiff(paths[-1], render(ortho, scene, seed=k))
    out = tmp_path / "m-dense.zarr"
    ds = mosaic(paths, reference=tmp_path / "ortho.tif", out=out, tile=128, client=client, dense=True, control_scenes=[0])
    assert len(json.loads(ds.attrs["scenes"])) == 2
    # model only: the same mosaic's adjusted models (the block adjustment does not depend on ``dense``:
    # a dense=False job's models are these, to the digit); dense: the positions the mosaic sampled
    errors = {}
    for dense, positions in ((False, None), (True, scene_positions(ds, out))):
        own, seam = mosaic_errors(ds, [s.to_ortho for s in STRIPS], [(SIZE, SIZE)] * 2, ORTHO, positions=positions)
        errors[dense] = (own, float(np.sqrt(np.mean(seam**2))))
    source, status, sigma_x, summary = (ds.source.values, ds.status.values, ds.sigma_x.values,
                                        json.loads(ds.attrs["summary"]))
    assert summary["control_points"][1] == 0 and summary["dense_refined"] == ["reference", "via 0"]
    assert "dense refinement per scene" in "\n".join(MosaicSummary(**summary).lines())

    def rms(e, mask):
        return float(np.sqrt(np.nanmean(e[mask] ** 2)))

    strip1 = source == 1  # strip 1's pixels, where its model and its dense positions are compared
    refined = strip1 & ((status == Status.MATCHED) | (status == Status.FILLED))
    estimated = strip1 & (status == Status.ESTIMATED)
    before, after = rms(errors[False][0], strip1), rms(errors[True][0], strip1)
    before_r, after_r = rms(errors[False][0], refined), rms(errors[True][0], refined)
    before_e, after_e = rms(errors[False][0], estimated), rms(errors[True][0], estimated)
    print(f"strip 1 (no control), its {strip1.sum()} px: RMSE {before:.3f} model only, {after:.3f} dense; "
          f"its {refined.sum()} px matched or filled via strip 0: {before_r:.3f} -> {after_r:.3f}; "
          f"its {estimated.sum()} px estimated along their scene rows: {before_e:.3f} -> {after_e:.3f}; "
          f"seam RMS {errors[False][1]:.3f} -> {errors[True][1]:.3f}")
    assert refined.sum() > 0.3 * strip1.sum() and estimated.sum() > 0.3 * strip1.sum()
    matched = strip1 & (status == Status.MATCHED)
    print(f"its {matched.sum()} px matched: {rms(errors[False][0], matched):.3f} -> {rms(errors[True][0], matched):.3f}")
    assert rms(errors[False][0], matched) > 0.5 and rms(errors[True][0], matched) < 0.15  # the turbulence, followed
    assert before_r > 0.5 and after_r < 0.35
    # beyond the overlap: each scene row's shift (from its matches) and the field's smooth part along the rows
    assert before_e > 0.5 and after_e < 0.3
    assert after < 0.25 < 0.5 < before
    assert errors[True][1] < 0.2 < errors[False][1]
    # the layers: a pixel matched against the neighbours has no known sigma (its match's would leave
    # out the neighbour's error: 5x optimistic, measured); the strip's model pixels keep the model's status
    assert np.isnan(sigma_x[strip1 & (status == Status.MATCHED)]).all()
    assert set(np.unique(status[strip1])) <= {Status.MATCHED, Status.FILLED, Status.ESTIMATED, Status.NO_TEXTURE,
                                              Status.BLUNDER, Status.MODEL}
