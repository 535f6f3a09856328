"""The mosaic's point finding: every scene's interest points and every pair's tie points, batched.

The registration finds the points of one pair in a sequence of tile-parallel rounds (coarse
alignment, correspondence pass 1, the guided passes). A block has hundreds of pairs; here each
round runs once for ALL of them:

1. :func:`scene_points`: the Foerstner candidates of every tile of every scene (and the
   reference) in one :meth:`~geocoder.pipeline.job.Job.run_tiles` stage; each scene's
   threshold ``f * mean(w)`` is applied on the client, so a scene's points are found once and
   reused by every pair it is in.
2. :func:`match_pairs`: the coarse alignments of all pairs in one stage (an overview shared
   by many pairs, the reference's, is computed once), then every correspondence pass as one
   stage holding one task per base tile of every pair still in play; the tie points are
   gathered per pair and each pair's robust polynomial is fitted on the client.

A pair goes through exactly the steps of :func:`geocoder.pipeline.register.find_tiepoints`
(the same tasks, the same checks, the same errors): only the scheduling differs. Every task's
result is kept by the job, so a killed run resumes at the round it was in.
"""

from __future__ import annotations

from dataclasses import dataclass

import dask
import numpy as np
import xarray as xr

from ..errors import GeocoderError, InputError, MatchingError
from ..kernels.interest import InterestPoints
from ..kernels.polynomial import PolyMap
from ..match.coarse import CoarseAlignment, Hypothesis
from ..match.tiepoints import TiePoints
from ..pipeline.coarse import _align, georeference_prior, overview, overview_factor
from ..pipeline.correspond import _tile_task, first_pass, fit_global, tile_points
from ..pipeline.detect import interest_points_many
from ..pipeline.job import Job
from ..pipeline.register import RegisterOptions, _check_overlap
from ..runtime import current_client
from ..scene import WindowReader
from ..tiles import TileGrid


@dataclass(frozen=True)
class PairSpec:
    """One pair to match: images ``base`` and ``dist`` (indices into the image list).

    ``prior`` (2x3 affine base pixel -> distorted pixel) starts the coarse alignment in
    place of the georeference, as in :func:`~geocoder.pipeline.coarse.coarse_alignment`.
    ``placed``: the prior comes from both images' placements by matching (within about a
    pixel): it is the coarse alignment (no task), and the first correspondence pass is guided
    by it (every interest point of the base matched where it predicts, as the later passes do).
    """

    name: str
    base: int
    dist: int
    prior: np.ndarray | None = None
    placed: bool = False


@dataclass
class _Pair:
    spec: PairSpec
    coarse: CoarseAlignment | None = None
    tiepoints: TiePoints | None = None
    mapping: PolyMap | None = None
    error: GeocoderError | None = None
    refined: bool = False  # its tie points refined by least squares (pass 1's pairs are not, when passes follow)
    first: InterestPoints | None = None  # the base points pass 1 pairs (thinned when unrefined on a large overlap)


def scene_points(job: Job, names: list[str], images: list[xr.DataArray], readers: list[WindowReader],
                 opts: RegisterOptions) -> list[InterestPoints]:
    """Interest points of every image, all tiles of all images in one tile-parallel stage.

    Parameters
    ----------
    job : Job
        Keeps every tile's candidates (a rerun skips them).
    names : list of str
        A name per image, unique (the tasks' keys).
    images : list of xarray.DataArray
        Ingested scenes ``(band, y, x)``; their chunks are the tiles.
    readers : list of WindowReader
        The same images in their Zarr stores: every task reads its tile and halo itself.
    opts : RegisterOptions
        ``band`` and ``interest`` are used.

    Returns
    -------
    list of InterestPoints
        Per image, the points :func:`~geocoder.pipeline.detect.interest_points` finds
        (the threshold ``f * mean(w)`` over the image's own tiles).
    """
    band = opts.band - 1
    return interest_points_many([image.data[band] for image in images], opts.interest, job=job, names=names,
                                readers=readers, bands=[band] * len(images), stage="interest-candidates",
                                phase="interest points (all scenes)")


def _overview_keys(spec: PairSpec, images: list[xr.DataArray], band: int, dist_band: int, max_size: int = 512
                   ) -> tuple[tuple[int, int, int], tuple[int, int, int], int]:
    """The overviews one pair's coarse alignment runs on, ``(image, band, factor)`` each, and the
    factor (as :func:`~geocoder.pipeline.coarse.submit_coarse_alignment` picks it)."""
    factor = overview_factor(images[spec.base], images[spec.dist], max_size)
    return (spec.base, band, factor), (spec.dist, dist_band, factor), factor


def _pair_tasks(pair: _Pair, grid: TileGrid, base_reader: WindowReader, dist_reader: WindowReader,
                bpts: InterestPoints, dpts: InterestPoints, predict: PolyMap, opts: RegisterOptions,
                guided: bool, refine: bool = True) -> dict:
    """One task per base tile of the pair that has points and maps into the distorted scene
    (the tasks of :func:`~geocoder.pipeline.correspond.match_tiles`), keyed ``<pair>.<tile>-<token>``."""
    copts = opts.correspondence
    band, dband = opts.band - 1, (opts.dist_band or opts.band) - 1
    dshape = dist_reader.shape[1:]
    token = dask.base.tokenize(base_reader.store, dist_reader.store, band, dband, predict.coef, copts, guided, refine)
    tasks = {}
    for tile, tile_bpts, tile_dpts, dwin in tile_points(grid, bpts, dpts, predict, dshape, copts):
        tasks[f"{pair.spec.name}.{tile.key}-{token[:12]}"] = dask.delayed(_tile_task, pure=True)(
            tile, base_reader, dist_reader, band, dband, tile_bpts, tile_dpts, predict, dwin,
            copts, guided, refine, dask_key_name=f"correspond-{pair.spec.name}-{tile.key}-{token}")
    return tasks


def coarse_alignments(job: Job, stage: str, specs: list[PairSpec], images: list[xr.DataArray],
                      opts: RegisterOptions) -> list:
    """The coarse alignments of many pairs, one task each, in one tile-parallel stage.

    Parameters
    ----------
    job : Job
        Keeps every task's result (a rerun resumes); the stage is ``<stage>-coarse``.
    stage : str
        Name of this batch.
    specs : list of PairSpec
        The pairs (names unique within the batch).
    images : list of xarray.DataArray
        Ingested scenes, indexed by ``PairSpec.base`` and ``dist``.
    opts : RegisterOptions
        ``band``, ``dist_band`` and ``use_georeference`` are used.

    Returns
    -------
    list
        Per pair, its :class:`~geocoder.match.coarse.CoarseAlignment`, or the
        :class:`~geocoder.errors.GeocoderError` saying why there is none.
    """
    band, dband = opts.band - 1, (opts.dist_band or opts.band) - 1
    todo = {s.name: (s, *_overview_keys(s, images, band, dband)) for s in specs if not s.placed}
    done = {}
    if todo:
        keys = {k for _, kb, kd, _ in todo.values() for k in (kb, kd)}
        arrays = {k: overview(images[k[0]].isel(band=k[1]), k[2]).data for k in sorted(keys)}
        client = current_client()
        if client is not None:
            # computed once, one chunk each: a graph per task would compute a shared overview (the
            # reference's) again for every pair (measured: 35 chunk reductions x 100 pairs)
            arrays = dict(zip(arrays, client.persist([a.rechunk(-1) for a in arrays.values()])))
        tasks = {}
        for name, (s, kb, kd, factor) in todo.items():
            prior = s.prior
            if prior is None and opts.use_georeference:
                prior = georeference_prior(images[s.base], images[s.dist])
            tasks[name] = dask.delayed(_align, pure=True)(arrays[kb], arrays[kd], factor, prior)
        done = job.run_tiles(f"{stage}-coarse", tasks, phase=f"coarse alignment ({stage})")
    return [CoarseAlignment(np.asarray(s.prior, dtype=np.float64)[:2], Hypothesis.PLACEMENT, False, False, 1, float("nan"))
            if s.placed else done[s.name] for s in specs]


def match_pairs(job: Job, stage: str, specs: list[PairSpec], images: list[xr.DataArray], readers: list[WindowReader],
                points: list[InterestPoints], opts: RegisterOptions) -> list:
    """Tie points of many pairs, each round of the registration's matching run once for all pairs.

    Parameters
    ----------
    job : Job
        Keeps every task's result (a rerun resumes).
    stage : str
        Name of this batch in the job's stages and the progress (e.g. ``"control"``).
    specs : list of PairSpec
        The pairs (names unique within the batch).
    images, readers : list
        Ingested scenes and their Zarr readers, indexed by ``PairSpec.base`` and ``dist``.
    points : list of InterestPoints
        Every image's interest points (:func:`scene_points`).
    opts : RegisterOptions
        Band, order, passes, fewest tie points and the correspondence options.

    Returns
    -------
    list
        Per pair, ``(tie points, mapping, coarse alignment)`` as
        :func:`~geocoder.pipeline.register.find_tiepoints` returns them, or the
        :class:`~geocoder.errors.GeocoderError` saying why the pair could not be matched.
    """
    pairs = [_Pair(s) for s in specs]
    if not pairs:
        return []
    coarse = dict(zip([s.name for s in specs], coarse_alignments(job, stage, specs, images, opts)))
    grids = {}
    for p in pairs:
        base, dist = images[p.spec.base], images[p.spec.dist]
        try:
            value = coarse[p.spec.name]
            if isinstance(value, GeocoderError):
                raise value
            _check_overlap(value.mapping, (base.sizes["y"], base.sizes["x"]), (dist.sizes["y"], dist.sizes["x"]),
                           base.attrs["source"], dist.attrs["source"])
            for pts, scene in ((points[p.spec.base], base), (points[p.spec.dist], dist)):
                if len(pts) < opts.min_tiepoints:
                    raise InputError(scene.attrs["source"], f"has too little texture: {len(pts)} interest points found")
        except GeocoderError as exc:
            p.error = exc
            continue
        p.coarse = value
        grids[p.spec.base] = TileGrid.from_chunks(base.data.chunks[1:])

    def round_(label: str, todo: list[_Pair], predicts: list[PolyMap], guided: bool, refine: list[bool] | None = None,
               first: bool = False) -> list[TiePoints]:
        """One correspondence pass of ``todo`` as one stage (pass 1's pairs refined per ``refine``,
        default all; ``first``: each pair's pass-1 base points); the tie points gathered per pair."""
        tasks, mine = {}, []
        for p, predict, r in zip(todo, predicts, refine or [True] * len(todo)):
            t = _pair_tasks(p, grids[p.spec.base], readers[p.spec.base], readers[p.spec.dist],
                            p.first if first else points[p.spec.base], points[p.spec.dist], predict, opts, guided, r)
            mine.append(list(t))
            tasks.update(t)
        done = job.run_tiles(f"{stage}-{label}", tasks, phase=f"correspondence {label} ({stage}, {len(todo)} pairs)")
        return [TiePoints.concatenate([done[k][0] for k in keys]) for keys in mine]

    def fail(p: _Pair, n: int) -> None:
        base, dist = images[p.spec.base], images[p.spec.dist]
        p.error = MatchingError(f"only {n} tie points found between {base.attrs['source']} and {dist.attrs['source']}")

    live = [p for p in pairs if p.error is None]
    # pass 1: pairs of interest points (seed 000 sec. 4.4) from the coarse prediction, left
    # unrefined on a pair with many points when guided passes follow, and thinned on a large
    # overlap (pipeline.correspond.first_pass, as in find_tiepoints); where that finds too
    # few but the coarse alignment is a full affine, guided from it instead; guided at once from
    # a placement
    found: dict[int, TiePoints] = {}
    for p in live:
        dist_shape = (images[p.spec.dist].sizes["y"], images[p.spec.dist].sizes["x"])
        p.first, p.refined = (points[p.spec.base], True) if p.spec.placed else first_pass(
            points[p.spec.base], p.coarse.mapping, dist_shape, order=opts.order, passes=opts.passes)
    for guided, todo in ((False, [p for p in live if not p.spec.placed]), (True, [p for p in live if p.spec.placed])):
        if todo:
            found.update(zip(map(id, todo), round_("pass-1-placed" if guided else "pass-1", todo,
                                                   [p.coarse.mapping for p in todo], guided, [p.refined for p in todo],
                                                   first=True)))
    retry = [p for p in live if len(found[id(p)]) < opts.min_tiepoints and p.coarse.affine]
    if retry:
        found.update(zip(map(id, retry), round_("pass-1-guided", retry, [p.coarse.mapping for p in retry], True)))
        for p in retry:
            p.refined = True
    for p in live:
        if len(found[id(p)]) < opts.min_tiepoints:
            fail(p, len(found[id(p)]))
        else:
            p.tiepoints, p.mapping = fit_global(found[id(p)], order=opts.order)
    # later passes: every base point of every pair matched from its fitted polynomial; a pair
    # that finds too few keeps the previous pass's points (and drops out of the later passes)
    live = [p for p in live if p.error is None]
    for i in range(1, opts.passes):
        if not live:
            break
        again = round_(f"pass-{i + 1}", live, [p.mapping for p in live], True)
        kept = []
        for p, tp in zip(live, again):
            if len(tp) >= opts.min_tiepoints:
                p.tiepoints, p.mapping = fit_global(tp, order=opts.order)
                p.refined = True
                kept.append(p)
        live = kept
    # a pair whose guided passes all found too few: pass 1's pairs refined, as its tie points
    todo = [p for p in pairs if p.error is None and not p.refined]
    if todo:
        for p, tp in zip(todo, round_("pass-1-refined", todo, [p.coarse.mapping for p in todo], False)):
            if len(tp) < opts.min_tiepoints:
                fail(p, len(tp))
            else:
                p.tiepoints, p.mapping = fit_global(tp, order=opts.order)
    return [p.error if p.error is not None else (p.tiepoints, p.mapping, p.coarse) for p in pairs]


__all__ = ["PairSpec", "coarse_alignments", "match_pairs", "scene_points"]
