"""The mosaic's batched point finding: one round of tile tasks for all pairs, the same points as pair by pair.

A 2 x 2 block of small scenes rendered from a synthetic orthoimage through known mappings
(:mod:`geocoder.simulate.block`), plus a noise image that is nowhere on the reference. Every
scene is ingested into a real job directory and matched on a real LocalCluster. The batched
stages (:func:`geocoder.mosaic.matching.scene_points`, :func:`~geocoder.mosaic.matching.match_pairs`)
must give exactly the interest points and tie points that the registration's own stages give
pair by pair, in a number of ``run_tiles`` rounds that does not depend on the number of pairs,
place every scene on the reference within a fraction of a pixel of the truth, and resume from
the job's kept tiles without computing anything again.
"""

from __future__ import annotations

import numpy as np
import pytest
from affine import Affine

from geocoder.errors import GeocoderError
from geocoder.kernels.polynomial import fit_polymap
from geocoder.mosaic.matching import PairSpec, match_pairs, scene_points
from geocoder.mosaic.placement import affine_between
from geocoder.pipeline.detect import interest_points
from geocoder.pipeline.job import Job
from geocoder.pipeline.register import RegisterOptions, RegisterSummary, _Timer, find_tiepoints, ingest_all
from geocoder.scene import WindowReader, open_scene, write_geotiff
from geocoder.simulate.block import BlockScene, render
from geocoder.simulate.texture import synthetic_ortho

pytestmark = pytest.mark.cluster

ORTHO = Affine(2.0, 0.0, 500000.0, 0.0, -2.0, 5800000.0)
SIZE = 192
TILE = 128
SCENES = [
    BlockScene(row0=r0, col0=c0, size=SIZE, angle_deg=a, scale=s, quadratic_px=q, gain=1.1 + 0.05 * k, offset=3.0 * k)
    for k, ((r0, c0), a, s, q) in enumerate(zip([(64, 64), (64, 180), (180, 64), (180, 180)], [2.0, -3.0, 1.5, -1.0],
                                                [1.0, 1.02, 0.98, 1.01], [1.0, -1.5, 0.8, 1.5]))
]


def _opened(job: Job, client, paths: list) -> tuple[list, list]:
    """Every image ingested into the job (the mosaic's first stage) and its window reader."""
    names = ["reference", *(f"scene-{k}" for k in range(len(paths) - 1))]
    images = list(ingest_all(job, {n: open_scene(p, chunks=TILE) for n, p in zip(names, paths)}, TILE, client).values())
    return images, [WindowReader(job.file(f"{n}.zarr")) for n in names]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("batched")
    ortho = np.squeeze(synthetic_ortho((480, 480), seed=4)).astype(np.float32)
    write_geotiff(d / "ortho.tif", ortho, transform=ORTHO, crs="EPSG:32633")
    paths = [d / "ortho.tif"]
    for k, scene in enumerate(SCENES):
        paths.append(d / f"scene{k}.tif")
        write_geotiff(paths[-1], render(ortho, scene, seed=k))
    paths.append(d / "noise.tif")
    write_geotiff(paths[-1], np.random.default_rng(3).normal(100, 20, (160, 160)).astype(np.float32))
    return d, paths


def _stages(job: Job, prefix: str) -> dict:
    return {k: v for k, v in job.tiles.items() if k.startswith(prefix)}


@pytest.mark.parametrize("thinned", [False, True], ids=["as-is", "pass-1-thinned"])
def test_batched_points_equal_pair_by_pair_in_a_fixed_number_of_rounds(files, client, tmp_path, monkeypatch, thinned):
    """``pass-1-thinned``: these small scenes made "large" (250 -> 2 points per term, 64 -> 32 px
    squares), so pass 1 is unrefined and thinned (441 -> 192 reference points for a scene) in the
    mosaic's batches and in find_tiepoints alike."""
    d, paths = files
    opts = RegisterOptions(tile=TILE, dense=False)
    if thinned:
        from geocoder.pipeline import correspond

        monkeypatch.setattr(correspond, "UNREFINED_POINTS_PER_TERM", 2)
        monkeypatch.setattr(correspond, "FIRST_PASS_CELL", 32)
    job = Job(str(tmp_path / "job"), "batched")
    images, readers = _opened(job, client, paths)
    n = len(images)

    # interest points: one stage for every tile of every image, the same points as image by image
    points = scene_points(job, ["reference", *(f"scene-{k}" for k in range(n - 1))], images, readers, opts)
    assert list(_stages(job, "interest")) == ["interest-candidates"]
    tiles = sum(len(im.data.chunks[1]) * len(im.data.chunks[2]) for im in images)
    assert job.tiles["interest-candidates"] == {"run": tiles, "skipped": 0}
    for image, reader, pts in zip(images, readers, points):
        alone = interest_points(image.data[0], opts.interest, reader=reader, band=0)
        assert len(pts) > 0
        np.testing.assert_array_equal(pts.x, alone.x)
        np.testing.assert_array_equal(pts.y, alone.y)
        np.testing.assert_array_equal(pts.w, alone.w)

    # every scene (and the noise) against the reference: coarse, pass 1 (and its guided retry for
    # the pairs that need it), pass 2 -- one round each for all five pairs
    specs = [PairSpec(f"ref-{k}", 0, k + 1) for k in range(n - 1)]
    if thinned:
        from geocoder.pipeline.correspond import first_pass_points

        identity = fit_polymap(points[0].x, points[0].y, points[0].x, points[0].y, order=1, robust=False)
        assert len(first_pass_points(points[0], identity, (480, 480), order=2)) < 0.5 * len(points[0])
    control = match_pairs(job, "control", specs, images, readers, points, opts)
    rounds = ["control-coarse", "control-pass-1", "control-pass-1-guided", "control-pass-2"]
    assert set(_stages(job, "control")) <= set(rounds) and {rounds[0], rounds[1], rounds[3]} <= set(_stages(job, "control"))
    assert job.tiles["control-coarse"]["run"] == len(specs)
    assert isinstance(control[-1], GeocoderError)  # the noise: reported for its pair, the others go on
    placed = control[:-1]
    for k, ((tp, mapping, coarse), scene) in enumerate(zip(placed, SCENES)):
        if k in (0, 3):  # the same tie points as the registration's stages find for this pair alone
            tp1, mapping1, coarse1 = find_tiepoints(images[0], images[k + 1], readers[0], readers[k + 1], opts,
                                                    RegisterSummary("", ""), _Timer(RegisterSummary("", "")),
                                                    points=(points[0], points[k + 1]))
            assert coarse.method == coarse1.method
            for col in ("base_x", "base_y", "dist_x", "dist_y", "inlier"):
                np.testing.assert_array_equal(getattr(tp, col), getattr(tp1, col))
            np.testing.assert_array_equal(mapping.coef, mapping1.coef)
        # and the scene sits where the simulator put it: reference pixel -> scene pixel against the truth
        good = tp.select(tp.inlier)
        assert len(good) >= opts.min_tiepoints
        tx, ty = scene.to_ortho(good.dist_x, good.dist_y)
        err = np.hypot(tx - good.base_x, ty - good.base_y)
        assert float(np.sqrt(np.mean(err**2))) < 0.15, (k, err)

    # the overlapping pairs of scenes, each predicted through the reference: three more rounds for all of them
    to_ref = [fit_polymap(tp.dist_x, tp.dist_y, tp.base_x, tp.base_y, order=2) for tp, _, _ in
              ((t.select(t.inlier), m, c) for t, m, c in placed)]
    ref_to = [m for _, m, _ in placed]
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    specs = [PairSpec(f"pair-{i}-{j}", i + 1, j + 1, affine_between(to_ref[i], ref_to[j], (SIZE, SIZE))) for i, j in pairs]
    ties = match_pairs(job, "ties", specs, images, readers, points, opts)
    assert {"ties-coarse", "ties-pass-1", "ties-pass-2"} <= set(_stages(job, "ties")) and len(_stages(job, "ties")) <= 4
    assert job.tiles["ties-coarse"]["run"] == len(pairs)
    for (i, j), spec, result in zip(pairs, specs, ties):
        if (i, j) in ((0, 1), (0, 3)):  # the same outcome as the registration's stages for this pair alone
            try:
                alone = find_tiepoints(images[i + 1], images[j + 1], readers[i + 1], readers[j + 1], opts,
                                       RegisterSummary("", ""), _Timer(RegisterSummary("", "")), prior=spec.prior,
                                       points=(points[i + 1], points[j + 1]))
            except GeocoderError as exc:
                alone = exc
            if isinstance(alone, GeocoderError):
                assert type(result) is type(alone) and str(result) == str(alone)
            else:
                np.testing.assert_array_equal(result[0].base_x, alone[0].base_x)
                np.testing.assert_array_equal(result[0].dist_y, alone[0].dist_y)
                np.testing.assert_array_equal(result[1].coef, alone[1].coef)
        if abs(i - j) == 3 or (i, j) == (1, 2):  # diagonal neighbours: a small overlap, maybe too few points
            if isinstance(result, GeocoderError):
                assert "tie points found between" in str(result)
                continue
        assert not isinstance(result, GeocoderError), (i, j, result)
        # the tie points join the same ground point in both scenes (the truth's mappings)
        good = result[0].select(result[0].inlier)
        ax, ay = SCENES[i].to_ortho(good.base_x, good.base_y)
        bx, by = SCENES[j].to_ortho(good.dist_x, good.dist_y)
        assert float(np.sqrt(np.mean((ax - bx) ** 2 + (ay - by) ** 2))) < 0.2, (i, j)
    job.release()

    # a rerun of the same job computes nothing again and gives the same points
    again = Job(str(tmp_path / "job"), "batched")
    images, readers = _opened(again, client, paths)
    points2 = scene_points(again, ["reference", *(f"scene-{k}" for k in range(n - 1))], images, readers, opts)
    control2 = match_pairs(again, "control", [PairSpec(f"ref-{k}", 0, k + 1) for k in range(n - 1)], images, readers,
                           points2, opts)
    ties2 = match_pairs(again, "ties", specs, images, readers, points2, opts)
    assert all(c["run"] == 0 and c["skipped"] > 0 for c in again.tiles.values()), again.tiles
    for a, b in zip(control + ties, control2 + ties2):
        if isinstance(a, GeocoderError):
            assert str(a) == str(b)
        else:
            np.testing.assert_array_equal(a[0].dist_x, b[0].dist_x)
    again.release()
