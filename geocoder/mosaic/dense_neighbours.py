"""Dense refinement of the scenes without control, against their refined neighbours.

``mosaic(dense=True)`` first refines every control scene densely against the reference
(:func:`geocoder.mosaic.refine.refine_scene`). A scene without control has only its adjusted model,
which cannot follow an airborne strip's scan-line turbulence. Here such a scene is matched
densely against a *neighbour composite*: its already-refined neighbours brought onto the
reference's pixel grid through their dense fields, radiometrically balanced, each pixel from
the neighbour that sees it nearest its centre among those whose field matched, filled or
estimated it (:mod:`geocoder.mosaic.scanlines`)
(where a neighbour has only its model, its turbulence is in it: the scene keeps its own model
there). The dense stage then runs exactly as against the reference (same grid,
predicted by the scene's adjusted model), seeded by the scene's tie points with those
neighbours, their neighbour side mapped onto the reference grid.

Order (:func:`refinement_rounds`): the control scenes, then rounds; in each round the scenes
not yet refined that share more tie points with the refined scenes than with any single
unrefined one are refined against all their refined neighbours.
Each composite is written one task per reference tile (only the tiles around the scene's
footprint) into the job directory, resumable (a sub-job per scene); a worker holds one tile's
windows, whatever the scene's size.

The field's ``sigma_x``, ``sigma_y`` (the mosaic's sigma layers at a matched pixel) are NaN,
unknown: the match's own sigma against the composite leaves out the neighbour's error (the
true error of a strip refined so was 5x its match sigma); propagating the neighbours' is not done.
"""

from __future__ import annotations

import dask
import numpy as np
import zarr
from affine import Affine

from ..geometry import pixel_to_world
from ..match.tiepoints import TiePoints
from ..pipeline.job import Job
from ..scene import IMAGE_VAR, WindowReader
from ..status import Status, positioned
from .block import Matches
from .compose import centre_score
from .output import footprint_box, scene_xy
from .projection import project_window

__all__ = ["neighbour_composite", "refine_by_neighbours", "refinement_rounds", "reference_positions", "tie_seeds"]


def refinement_rounds(n_scenes: int, refined: set[int], ties: dict[tuple[int, int], int]) -> list[list[tuple[int, list[int]]]]:
    """The order of the neighbour refinement: rounds of ``(scene, refined neighbours)``.

    A scene waits for a better neighbour: it is refined in a round when its tie points with
    the refined scenes are at least as many as with any single scene not refined yet (a strip
    that barely overlaps a refined strip waits for the strip beside it). When no scene
    qualifies, those with the most tie points to refined scenes go.

    Parameters
    ----------
    n_scenes : int
        Scenes of the block (indices ``0 .. n_scenes - 1``).
    refined : set of int
        Scenes refined before (against the reference).
    ties : dict
        ``(i, j) -> number of tie points`` of every pair of scenes that shares some.

    Returns
    -------
    list of list of tuple
        Per round, every scene refined in it (ascending) with its neighbours refined in
        earlier rounds (ascending). Scenes connected to no refined scene are in no round.
    """
    near: dict[int, dict[int, int]] = {k: {} for k in range(n_scenes)}
    for (i, j), count in ties.items():
        if count > 0:
            near[i][j] = near[i].get(j, 0) + count
            near[j][i] = near[j].get(i, 0) + count
    done, rounds = set(refined), []
    while True:
        open_ = {k: sum(c for m, c in near[k].items() if m in done) for k in range(n_scenes)
                 if k not in done and set(near[k]) & done}
        if not open_:
            return rounds
        ready = [k for k, c in open_.items() if c >= max((c2 for m, c2 in near[k].items() if m not in done), default=0)]
        if not ready:
            best = max(open_.values())
            ready = [k for k, c in open_.items() if c == best]
        rounds.append([(k, sorted(set(near[k]) & done)) for k in sorted(ready)])
        done |= set(ready)


def _field_at(located: dict, rx: np.ndarray, ry: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A dense field's displacement at the nearest sample of scattered reference pixels, and
    whether it is matched or filled there (only the chunks holding the points are read)."""
    a = np.rint(ry).astype(np.int64) - located["row0"]
    b = np.rint(rx).astype(np.int64) - located["col0"]
    inside = (a >= 0) & (a < located["shape"][0]) & (b >= 0) & (b < located["shape"][1])
    dx, dy = np.zeros(rx.shape), np.zeros(rx.shape)
    good = np.zeros(rx.shape, dtype=bool)
    if inside.any():
        g = zarr.open_group(located["store"], mode="r")
        sel = (a[inside], b[inside])
        status = np.asarray(g["status"].vindex[sel])
        good[inside] = (status == Status.MATCHED) | (status == Status.FILLED)
        dx[inside] = g["dx"].vindex[sel]
        dy[inside] = g["dy"].vindex[sel]
    return dx, dy, good


def _refined_at(model, params: np.ndarray, located: dict | None, transform: Affine, rx: np.ndarray, ry: np.ndarray,
                dem=None) -> tuple[np.ndarray, np.ndarray]:
    """Scene position of scattered reference pixels: the dense field where it matched or
    filled the pixel (as :func:`geocoder.mosaic.output.scene_xy`), the adjusted model elsewhere."""
    ex, ny = pixel_to_world(transform, rx, ry)
    hz = np.zeros(ex.shape) if dem is None else np.asarray(dem(ex, ny), dtype=np.float64)
    x, y = project_window(model, params, ex[:, None], ny[:, None], hz[:, None], step=1)
    x, y = x[:, 0], y[:, 0]
    if located is None:
        return x, y
    dx, dy, good = _field_at(located, rx, ry)
    return np.where(good, rx + dx, x), np.where(good, ry + dy, y)


def reference_positions(xy: np.ndarray, to_ref, model, params: np.ndarray, located: dict | None, transform: Affine,
                        dem=None, *, iterations: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Reference pixels of scene pixels, through the scene's refined positions (their inverse).

    Parameters
    ----------
    xy : ndarray, shape (n, 2)
        Scene pixels (column, row).
    to_ref : callable
        ``to_ref(x, y) -> (rx, ry)``: an approximate scene -> reference mapping (the start,
        and its Jacobian the Newton step's).
    model, params
        The scene's adjusted model and parameters (map ``E, N, h`` -> scene pixel).
    located : dict or None
        The scene's dense field (as :func:`geocoder.mosaic.output.scene_xy` takes it), or None.
    transform : affine.Affine
        The reference's transform.
    dem : callable, optional
        ``dem(E, N) -> h``.
    iterations : int
        Newton steps.

    Returns
    -------
    rx, ry : ndarray, shape (n,)
        Reference column and row whose refined position in the scene is ``xy``.
    """
    x, y = np.asarray(xy[:, 0], dtype=np.float64), np.asarray(xy[:, 1], dtype=np.float64)
    rx, ry = to_ref(x, y)
    ax, ay = to_ref(x + 1.0, y)
    bx, by = to_ref(x, y + 1.0)
    j11, j21, j12, j22 = ax - rx, ay - ry, bx - rx, by - ry  # d(reference) / d(scene)
    for _ in range(iterations):
        sx, sy = _refined_at(model, params, located, transform, rx, ry, dem)
        ex, ey = x - sx, y - sy
        rx, ry = rx + j11 * ex + j12 * ey, ry + j21 * ex + j22 * ey
    return rx, ry


def tie_seeds(n: int, neighbours: list[int], ties: list[Matches], to_ref: list, models: list, fields: list,
              transform: Affine, dem=None) -> TiePoints:
    """Tie points of scene ``n`` with its refined neighbours, as reference pixel -> scene ``n`` pixel.

    Each tie's neighbour side is mapped onto the reference grid through the neighbour's refined
    positions (:func:`reference_positions`) and rounded to the pixel the dense stage seeds;
    scene ``n``'s side is moved by the same offset through the inverse of ``to_ref[n]``'s Jacobian.

    Parameters
    ----------
    n : int
        The scene refined (block index).
    neighbours : list of int
        Its refined neighbours (block indices).
    ties : list of Matches
        Tie points between block scenes (``i``, ``j`` block indices).
    to_ref, models, fields : list
        Per block scene: scene -> reference mapping, ``(model, params)``, dense field location or None.
    transform : affine.Affine
        The reference's transform.
    dem : callable, optional
        ``dem(E, N) -> h``.

    Returns
    -------
    TiePoints
        ``base``: reference pixels (integers), ``dist``: scene ``n`` pixels.
    """
    base, dist, sig = [], [], []
    for t in ties:
        if {t.i, t.j} & {n} and ({t.i, t.j} - {n}) & set(neighbours):
            k, a, b = (t.j, t.b, t.a) if t.i == n else (t.i, t.a, t.b)
            rx, ry = reference_positions(a, to_ref[k], *models[k], fields[k], transform, dem)
            base.append(np.column_stack([rx, ry]))
            dist.append(b)
            sig.append(t.sigma)
    if not base:
        return TiePoints.empty()
    base_, dist_, sig_ = np.concatenate(base), np.concatenate(dist), np.concatenate(sig)
    ok = np.all(np.isfinite(base_), axis=1)
    base_, dist_, sig_ = base_[ok], dist_[ok], sig_[ok]
    x, y = dist_[:, 0], dist_[:, 1]
    rx, ry = to_ref[n](x, y)
    ax, ay = to_ref[n](x + 1.0, y)
    bx, by = to_ref[n](x, y + 1.0)
    j11, j21, j12, j22 = ax - rx, ay - ry, bx - rx, by - ry
    det = j11 * j22 - j12 * j21
    px, py = np.rint(base_[:, 0]), np.rint(base_[:, 1])
    ex, ey = px - base_[:, 0], py - base_[:, 1]
    dx, dy = (j22 * ex - j12 * ey) / det, (-j21 * ex + j11 * ey) / det
    return TiePoints.build(base_x=px, base_y=py, dist_x=x + dx, dist_y=y + dy, weight=np.ones(px.size),
                           rho=np.ones(px.size), sigma_x=sig_[:, 0], sigma_y=sig_[:, 1])


def _composite_tile(store: str, window: tuple[int, int, int, int], transform: Affine, models: list, readers: list,
                    shapes: list, fields: list, gains: np.ndarray, dem=None, method: str = "bilinear") -> None:
    """Write one reference tile of the neighbour composite: each pixel from the neighbour
    that sees it nearest its centre among those whose dense field matched or filled it, at
    that position, balanced. A neighbour's model-only pixels are left out: they carry its
    turbulence, which the scene matched against them would inherit."""
    from .layers import field_layers
    r0, r1, c0, c1 = window
    heights = None
    if dem is not None:
        ys, xs = np.mgrid[r0:r1, c0:c1].astype(np.float64)
        heights = dem(*pixel_to_world(transform, xs, ys))
    nb = readers[0].shape[0]
    out = np.full((nb, r1 - r0, c1 - c0), np.nan, dtype=np.float32)
    best = np.full((r1 - r0, c1 - c0), np.inf)
    for (model, params), reader, shape, located, gain in zip(models, readers, shapes, fields, gains):
        x, y = scene_xy(model, params, transform, window, located, (0, 0), heights)
        s = centre_score(x, y, shape)
        codes = field_layers(located, window, (0, 0))[0]
        take = (s <= 1.0) & (s < best) & positioned(codes)
        if not take.any():
            continue
        v = gain[:, 0, None, None] * reader.sample(x, y, method=method) + gain[:, 1, None, None]
        take &= np.all(np.isfinite(v), axis=0)
        out = np.where(take[None], v, out)
        best = np.where(take, s, best)
    zarr.open_group(store, mode="r+")[IMAGE_VAR][:, r0:r1, c0:c1] = out


def neighbour_composite(job: Job, name: str, ref_shape: tuple[int, int], chunks: tuple, box: tuple[int, int, int, int],
                        transform: Affine, models: list, readers: list, shapes: list, fields: list, gains: np.ndarray,
                        dem=None) -> WindowReader:
    """The refined neighbours of a scene on the reference grid, as a reader the dense stage takes.

    Parameters
    ----------
    job : Job
        The scene's sub-job: the composite's store is in its directory, its tiles resumable.
    name : str
        Stage name of its tiles.
    ref_shape : tuple of int
        Rows and columns of the reference.
    chunks : tuple
        The reference's chunks ``(rows, cols)`` (dask chunks): the composite's tiles.
    box : tuple of int
        ``row0, row1, col0, col1`` (reference pixels) around the scene's footprint: only the
        tiles meeting it are computed; elsewhere the composite is NaN.
    transform : affine.Affine
        The reference's transform.
    models, readers, shapes, fields, gains
        Per neighbour: ``(model, params)``, scene reader, shape, dense field location (or
        None) and ``(bands, 2)`` gain and offset.
    dem : callable, optional
        ``dem(E, N) -> h``.

    Returns
    -------
    WindowReader
        Over the composite's ``image (band, y, x)``, float32, NaN where no neighbour's field
        matched or filled the pixel.
    """
    store = job.file(f"{name}.zarr")
    edges_r, edges_c = np.r_[0, np.cumsum(chunks[0])], np.r_[0, np.cumsum(chunks[1])]
    nb = readers[0].shape[0]
    if not job.done(f"{name}-created"):
        g = zarr.open_group(store, mode="w", zarr_format=3)
        g.create_array(IMAGE_VAR, shape=(nb, *ref_shape), chunks=(nb, int(chunks[0][0]), int(chunks[1][0])),
                       dtype=np.float32, fill_value=np.nan)
        job.save(f"{name}-created")
    r0, r1, c0, c1 = box
    tasks = {}
    for a in range(len(chunks[0])):
        for b in range(len(chunks[1])):
            w = (int(edges_r[a]), int(edges_r[a + 1]), int(edges_c[b]), int(edges_c[b + 1]))
            if w[0] < r1 and w[1] > r0 and w[2] < c1 and w[3] > c0:
                tasks[f"{a}-{b}"] = dask.delayed(_composite_tile, pure=True)(
                    store, w, transform, models, readers, shapes, fields, gains, dem)
    job.run_tiles(name, tasks)
    return WindowReader(store)


#: Margin (reference pixels) of a neighbour composite around the scene's footprint: the
#: dense stage's template and search reach past the footprint's edge.
COMPOSITE_MARGIN = 32


def refine_by_neighbours(job: Job, key: str, store: str, ref, transform: Affine, readers: list, models: list,
                         shapes: list, to_ref: list, fields: list, gains: np.ndarray, ties: list[Matches],
                         opts, concurrently, dem=None, passes: int = 2) -> dict[int, list[int]]:
    """Refine the scenes without a field densely against their refined neighbours, in rounds.

    Parameters
    ----------
    job : Job
        The mosaic's job (every scene gets sub-jobs in its ``dense`` directory).
    key : str
        The mosaic's job key.
    store : str
        The output store: the fields are written to its groups ``dense/<n>``.
    ref : xarray.DataArray
        The ingested reference (its shape and chunks are the dense stage's grid).
    transform : affine.Affine
        The reference's transform.
    readers, models, shapes, to_ref : list
        Per block scene: reader, ``(model, params)``, shape, scene -> reference mapping.
    fields : list
        Per block scene, its dense field's location or None; updated in place.
    gains : ndarray, shape (K, bands, 2)
        Radiometric gain and offset per block scene and band.
    ties : list of Matches
        Tie points between block scenes (block indices).
    opts : RegisterOptions
        The mosaic's options (band, tile).
    concurrently : callable
        ``concurrently(fn, items, phase) -> results``: runs the scenes of one round at once.
    dem : callable, optional
        ``dem(E, N) -> h``.
    passes : int
        Passes over the rounds. The first refines each scene against the neighbours refined in
        earlier rounds; every further one again, in the same order, against all its refined
        neighbours but those of its own round (a field is not read while it is rewritten), so
        that a scene refined early also gets the neighbours refined after it (group
        ``dense/<n>-<pass>``); skipped where those neighbours and their fields are the ones
        it was matched against.

    Returns
    -------
    dict
        Block index of every scene refined here -> the neighbours it was last refined against.
    """
    from .refine import refine_scene
    chunks = ref.data.chunks[1:]
    ref_shape = (ref.sizes["y"], ref.sizes["x"])
    via: dict[int, list[int]] = {}

    def one(item):
        n, near, tag = item
        sub = Job(job.file("dense", f"neighbours-{n}{tag}"), key)
        try:
            r0, r1, c0, c1 = footprint_box(to_ref[n], shapes[n], (0, 0), margin=COMPOSITE_MARGIN)
            base = neighbour_composite(sub, "composite", ref_shape, chunks, (r0, r1, c0, c1), transform,
                                       [models[k] for k in near], [readers[k] for k in near], [shapes[k] for k in near],
                                       [fields[k] for k in near], gains[near], dem)
        finally:
            sub.release()
        seeds = tie_seeds(n, near, ties, to_ref, models, fields, transform, dem)
        if len(seeds) == 0:
            return None
        return refine_scene(job, key, store, n, ref, base, readers[n], models[n], seeds, to_ref[n], shapes[n], transform,
                       opts, dem, tag, sigma_known=False)

    counts: dict[tuple[int, int], int] = {}
    for t in ties:
        counts[(t.i, t.j)] = counts.get((t.i, t.j), 0) + len(t)
    rounds = refinement_rounds(len(models), {n for n, f in enumerate(fields) if f is not None}, counts)
    near_all: dict[int, set[int]] = {}
    for i, j in counts:
        near_all.setdefault(i, set()).add(j)
        near_all.setdefault(j, set()).add(i)
    version = [0] * len(fields)  # how often each scene's field was replaced
    used: dict[int, list[tuple[int, int]]] = {}  # the neighbours' versions a scene's field was matched against
    for p in range(passes):
        for r, this in enumerate(rounds):
            if p == 0:
                items = [(n, [k for k in near if fields[k] is not None], "") for n, near in this]
            else:
                same = {n for n, _ in this}
                items = [(n, sorted(k for k in near_all[n] - same if fields[k] is not None), f"-{p + 1}")
                         for n, _ in this if n in via]
                items = [item for item in items if [(k, version[k]) for k in item[1]] != used[item[0]]]
            items = [item for item in items if item[1]]
            phase = f"dense refinement via neighbours (pass {p + 1}, round {r + 1})"
            for (n, near, _), f in zip(items, concurrently(one, items, phase)):
                if f is not None:
                    fields[n] = f
                    version[n] += 1
                    used[n] = [(k, version[k]) for k in near]
                    via[n] = near
    return via
