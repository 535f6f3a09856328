"""Placing the scenes the reference does not find: matched against the placed scenes they may overlap.

A scene can miss the reference: it is small next to it (the blind coarse alignment runs on an
overview), the reference is untextured, cloudy or nodata where it lies, or it lies partly
outside. :func:`place_by_neighbours` then matches every such scene against the scenes already
placed (the same batched rounds as the reference pass, :func:`~geocoder.mosaic.matching.match_pairs`:
one stage per round for all pairs) and chains its mapping to the reference through theirs.
A scene with a georeference or sensor model is matched with the placed scenes it says it
overlaps, from that prior; one with neither with every placed scene, its offset searched first
(:func:`search_offsets`). Scenes placed in one round are candidates in the next, so a chain of
scenes is placed scene by scene; the passes stop when a round places nothing new.

A scene placed so has no control points: the block adjustment carries it by its tie points.
Its mapping to the reference is fitted on the overlap only (an affine, extrapolated over the
rest); after the adjustment, :func:`footprint_from_model` gives it the footprint of its
adjusted model.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import xarray as xr

from ..errors import GeocoderError
from ..geometry import pixel_to_world
from ..kernels.interest import InterestPoints
from ..kernels.polynomial import PolyMap, fit_polymap
from ..pipeline.job import Job
from ..pipeline.register import RegisterOptions
from ..scene import WindowReader
from .matching import PairSpec, coarse_alignments, match_pairs

#: Fraction of either scene's footprint (a grid of samples) inside the other for a pair to be tried,
#: when the unplaced scene's position is known from its georeference or sensor model.
MIN_OVERLAP = 0.02


@dataclass
class Placement:
    """How the scenes missing from the reference were placed.

    Attributes
    ----------
    via : dict
        Scene index -> the placed scene it was placed through (the one with the most tie points).
    ties : dict
        Scene index -> tie points per neighbour it was matched with: ``{neighbour: n}``.
    tried : dict
        Scene index -> the placed scenes it was tried against, for the scenes that stay unplaced.
    failed : dict
        Scene index -> ``{neighbour: why the pair could not be matched}``.
    notes : dict
        Scene index -> why it was not tried at all (e.g. too little texture).
    rounds : int
        Matching rounds run.
    """

    via: dict[int, int] = field(default_factory=dict)
    ties: dict[int, dict[int, int]] = field(default_factory=dict)
    tried: dict[int, list[int]] = field(default_factory=dict)
    failed: dict[int, dict[int, str]] = field(default_factory=dict)
    notes: dict[int, str] = field(default_factory=dict)

    def why_not(self, u: int) -> str:
        """Why scene ``u`` was not placed by a neighbour.

        Parameters
        ----------
        u : int
            Scene index.

        Returns
        -------
        str
        """
        if u in self.notes:
            return self.notes[u]
        failed = self.failed.get(u, {})
        if not failed:
            return "no placed scene overlaps it"
        return f"matched in vain with scene(s) {', '.join(map(str, sorted(failed)))}: {next(iter(failed.values()))}"
    rounds: int = 0


def _samples(shape: tuple[int, int], samples: int) -> tuple[np.ndarray, np.ndarray]:
    h, w = shape
    ys, xs = np.meshgrid(np.linspace(0, h - 1, samples), np.linspace(0, w - 1, samples), indexing="ij")
    return xs.ravel(), ys.ravel()


def _affine(coef: np.ndarray) -> Callable:
    """A 2x3 affine ``(x, y) -> (x', y')`` as a mapping."""
    def f(x, y):
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        return coef[0, 0] * x + coef[0, 1] * y + coef[0, 2], coef[1, 0] * x + coef[1, 1] * y + coef[1, 2]

    return f


def _inverse(coef: np.ndarray) -> np.ndarray:
    full = np.vstack([coef, [0.0, 0.0, 1.0]])
    return np.linalg.inv(full)[:2]


def overlap_fraction(i_shape: tuple[int, int], i_to_ref: Callable, ref_to_j: Callable, j_shape: tuple[int, int],
                     samples: int = 16) -> float:
    """Fraction of scene ``i`` (a grid of samples) that falls inside scene ``j``.

    Parameters
    ----------
    i_shape : (rows, cols)
        Scene ``i``'s size.
    i_to_ref, ref_to_j : callable
        Scene ``i`` pixel -> reference pixel, reference pixel -> scene ``j`` pixel.
    j_shape : (rows, cols)
        Scene ``j``'s size.
    samples : int
        Samples per side of the grid.

    Returns
    -------
    float
    """
    rx, ry = i_to_ref(*_samples(i_shape, samples))
    jx, jy = ref_to_j(rx, ry)
    inside = (jx >= 0) & (jx <= j_shape[1] - 1) & (jy >= 0) & (jy <= j_shape[0] - 1)
    return float(inside.mean())


def affine_between(i_to_ref: Callable, ref_to_j: Callable, shape: tuple[int, int], samples: int = 9) -> np.ndarray:
    """Affine scene ``i`` pixel -> scene ``j`` pixel through the reference (2x3), fitted on a grid of scene ``i``.

    Parameters
    ----------
    i_to_ref, ref_to_j : callable
        Scene ``i`` pixel -> reference pixel, reference pixel -> scene ``j`` pixel.
    shape : (rows, cols)
        Scene ``i``'s size.
    samples : int

    Returns
    -------
    ndarray, shape (2, 3)
    """
    xs, ys = _samples(shape, samples)
    jx, jy = ref_to_j(*i_to_ref(xs, ys))
    design = np.column_stack([xs, ys, np.ones(xs.size)])
    return np.linalg.lstsq(design, np.column_stack([jx, jy]), rcond=None)[0].T


def _candidates(u: int, placed: list[int], tried: set[int], shapes: list, to_ref: dict, ref_to: dict,
                prior: np.ndarray | None) -> list[tuple[int, np.ndarray | None]]:
    """The placed scenes scene ``u`` is matched with this round, each with its coarse prior.

    With ``prior`` (reference pixel -> scene ``u`` pixel, from the scene's georeference or
    sensor model), only the placed scenes whose footprint it overlaps; without, every placed
    scene not tried yet (the coarse alignment searches blind).
    """
    out = []
    for j in placed:
        if j in tried:
            continue
        if prior is None:
            out.append((j, None))
            continue
        ref_to_u, u_to_ref = _affine(prior), _affine(_inverse(prior))
        if max(overlap_fraction(shapes[j], to_ref[j], ref_to_u, shapes[u]),
               overlap_fraction(shapes[u], u_to_ref, ref_to[j], shapes[j])) < MIN_OVERLAP:
            continue
        out.append((j, affine_between(to_ref[j], ref_to_u, shapes[j])))
    return out


#: Offsets of the translation hypotheses of :func:`search_offsets`, in fractions of the placed scene's size.
OFFSETS = (0.5, 0.75)


def search_offsets(job: Job, stage: str, pairs: list[tuple[int, int]], images: list[xr.DataArray],
                   opts: RegisterOptions) -> dict:
    """Coarse alignment of pairs of scenes that nothing places relative to each other.

    The blind coarse alignment (Fourier-Mellin, phase correlation over the whole images)
    finds two scenes of one size reliably only where they overlap by more than half: the
    correlation windows taper both images towards their edges, where a smaller overlap
    lies. So each pair also gets translation hypotheses, scene ``u`` beside scene ``j`` in
    each of the 8 directions by :data:`OFFSETS` of ``j``'s size, each refined by the coarse
    alignment from there (:func:`~geocoder.mosaic.matching.coarse_alignments`, all
    hypotheses of all pairs in one stage); the highest correlation peak wins.

    Parameters
    ----------
    job : Job
        Keeps every task's result; the stage is ``<stage>-coarse``.
    stage : str
        Name of this batch.
    pairs : list of (j, u)
        Scene indices: ``j`` placed, ``u`` to find (image ``k + 1`` is scene ``k``).
    images : list of xarray.DataArray
        The reference and the scenes.
    opts : RegisterOptions

    Returns
    -------
    dict
        ``(j, u)`` -> the affine scene ``j`` pixel -> scene ``u`` pixel (2x3) of the best
        hypothesis, or the :class:`~geocoder.errors.GeocoderError` of the blind search when
        no hypothesis gives an alignment.
    """
    specs, keys = [], []
    for j, u in pairs:
        h, w = images[j + 1].sizes["y"], images[j + 1].sizes["x"]
        hypotheses = [None] + [np.array([[1.0, 0.0, -f * dx * w], [0.0, 1.0, -f * dy * h]])
                               for f in OFFSETS for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy]
        for n, prior in enumerate(hypotheses):
            specs.append(PairSpec(f"near-{j}-{u}-{n}", j + 1, u + 1, prior))
            keys.append((j, u))
    out: dict = {}
    for key, result in zip(keys, coarse_alignments(job, stage, specs, images, opts)):
        if isinstance(result, GeocoderError):
            out.setdefault(key, result)
        elif isinstance(out.get(key), GeocoderError) or key not in out or result.peak > out[key].peak:
            out[key] = result
    return {k: v if isinstance(v, GeocoderError) else v.matrix for k, v in out.items()}


def place_by_neighbours(job: Job, images: list[xr.DataArray], readers: list[WindowReader], points: list[InterestPoints],
                        opts: RegisterOptions, shapes: list[tuple[int, int]], to_ref: dict[int, PolyMap],
                        ref_to: dict[int, PolyMap], priors: list[np.ndarray | None]) -> Placement:
    """Place the scenes missing from ``to_ref`` by matching them against the placed scenes, chained.

    Every round matches every unplaced scene against the placed scenes it may overlap and
    has not been tried with (one batch of :func:`~geocoder.mosaic.matching.match_pairs`:
    tile-parallel, one stage per step for all pairs; the pairs without a prior have their
    offset searched first, :func:`search_offsets`, one more stage); a scene matched with one or more of
    them gets a mapping to the reference through theirs (their tie points' positions on the
    reference, an affine fitted robustly). Rounds repeat while one places a scene.

    Parameters
    ----------
    job : Job
        Keeps every task's result (a rerun resumes; the rounds are named ``neighbours-<n>``).
    images, readers : list
        The reference and the scenes (image ``k + 1`` is scene ``k``) and their Zarr readers.
    points : list of InterestPoints
        Every image's interest points.
    opts : RegisterOptions
        As for the reference pass.
    shapes : list of (rows, cols)
        Every scene's size.
    to_ref, ref_to : dict
        Scene index -> scene pixel -> reference pixel and back, for the scenes placed so far;
        completed in place with the scenes this places.
    priors : list
        Per scene, its affine reference pixel -> scene pixel (2x3) from its georeference or
        sensor model, or None (then it is tried against every placed scene).

    Returns
    -------
    Placement
        Which neighbour placed each scene, the tie points per neighbour, what was tried.
    """
    placement = Placement()
    unplaced = [k for k in range(len(shapes)) if k not in to_ref]
    for u in [u for u in unplaced if len(points[u + 1]) < opts.min_tiepoints]:  # no search where nothing can match
        placement.notes[u] = f"too little texture to match it: {len(points[u + 1])} interest points"
        unplaced.remove(u)
    tried: dict[int, set[int]] = {u: set() for u in unplaced}
    while unplaced and to_ref:
        todo = []
        for u in unplaced:
            near = _candidates(u, sorted(to_ref), tried[u], shapes, to_ref, ref_to, priors[u])
            todo += [(j, u, prior) for j, prior in near]
            tried[u].update(to_ref)
        if not todo:
            break
        stage = f"neighbours-{placement.rounds}"
        blind = [(j, u) for j, u, prior in todo if prior is None]
        searched = search_offsets(job, f"{stage}-search", blind, images, opts)
        specs, keys = [], []
        for j, u, prior in todo:
            if prior is None and isinstance(searched[j, u], GeocoderError):
                placement.failed.setdefault(u, {})[j] = str(searched[j, u])
                continue
            specs.append(PairSpec(f"near-{j}-{u}", j + 1, u + 1, searched[j, u] if prior is None else prior))
            keys.append((j, u))
        found = match_pairs(job, stage, specs, images, readers, points, opts)
        placement.rounds += 1
        matched: dict[int, list] = {}
        for (j, u), result in zip(keys, found):
            if isinstance(result, GeocoderError):
                placement.failed.setdefault(u, {})[j] = str(result)
            else:
                tp = result[0]
                matched.setdefault(u, []).append((j, tp.select(tp.inlier)))
        if not matched:
            break
        for u, found_u in sorted(matched.items()):
            ux = np.concatenate([tp.dist_x for _, tp in found_u])
            uy = np.concatenate([tp.dist_y for _, tp in found_u])
            rx, ry = (np.concatenate(v) for v in zip(*(to_ref[j](tp.base_x, tp.base_y) for j, tp in found_u)))
            # fitted on the overlap only: an affine, which extrapolates over the rest of the scene
            to_ref[u] = fit_polymap(ux, uy, rx, ry, order=1)
            ref_to[u] = fit_polymap(rx, ry, ux, uy, order=1)
            placement.ties[u] = {j: len(tp) for j, tp in found_u}
            placement.via[u] = max(found_u, key=lambda m: len(m[1]))[0]
        unplaced = [u for u in unplaced if u not in matched]
    placement.tried = {u: sorted(tried.get(u, ())) for u in range(len(shapes)) if u not in to_ref}
    return placement


def footprint_from_model(model, params: np.ndarray, transform, to_ref: Callable, shape: tuple[int, int],
                         height: Callable | None = None, *, samples: int = 48) -> tuple[PolyMap, PolyMap]:
    """Scene pixel <-> reference pixel from a scene's adjusted model, over its whole footprint.

    A grid of reference pixels over the footprint ``to_ref`` gives (grown by a quarter of its
    size each side, twice: the approximate footprint may be off far from where it was fitted)
    is projected into the scene by the model; cubic polynomials are fitted both ways to the
    samples inside the scene.

    Parameters
    ----------
    model, params
        The adjusted model (map ground ``(E, N, h)`` -> scene pixel) and its parameters.
    transform : Affine
        The reference's transform.
    to_ref : callable
        Approximate scene pixel -> reference pixel.
    shape : (rows, cols)
        The scene's size.
    height : callable, optional
        ``height(E, N)``: the DEM; 0 without.
    samples : int
        Samples per side of the grid.

    Returns
    -------
    (PolyMap, PolyMap)
        Scene pixel -> reference pixel and reference pixel -> scene pixel; ``to_ref``
        itself (and its fit back) if too few samples land in the scene.
    """
    h, w = shape
    current, back = to_ref, None
    for _ in range(2):
        rx, ry = current(*_samples(shape, 17))
        grow_x, grow_y = 0.25 * np.ptp(rx), 0.25 * np.ptp(ry)
        gy, gx = np.meshgrid(np.linspace(ry.min() - grow_y, ry.max() + grow_y, samples),
                             np.linspace(rx.min() - grow_x, rx.max() + grow_x, samples), indexing="ij")
        ex, ny = pixel_to_world(transform, gx.ravel(), gy.ravel())
        hz = np.zeros(ex.size) if height is None else np.asarray(height(ex, ny), dtype=np.float64)
        xy = model.project(params, np.column_stack([ex, ny, hz]))
        inside = (np.all(np.isfinite(xy), axis=1) & (xy[:, 0] >= 0) & (xy[:, 0] <= w - 1)
                  & (xy[:, 1] >= 0) & (xy[:, 1] <= h - 1))
        if inside.sum() < 30:
            break
        sx, sy, bx, by = xy[inside, 0], xy[inside, 1], gx.ravel()[inside], gy.ravel()[inside]
        current = fit_polymap(sx, sy, bx, by, order=3, robust=False)
        back = fit_polymap(bx, by, sx, sy, order=3, robust=False)
    if back is None:
        sx, sy = _samples(shape, 17)
        bx, by = to_ref(sx, sy)
        back = fit_polymap(bx, by, sx, sy, order=3, robust=False)
    return current, back


__all__ = ["Placement", "affine_between", "footprint_from_model", "overlap_fraction", "place_by_neighbours",
           "search_offsets"]
