"""Tile-parallel dense matching: region growing with halo exchange between tiles.

Round 0 seeds every tile with the tie points in its core. A task grows matches inside its
tile plus a halo, writes the matches of its core into the state store (Zarr, chunk = tile,
so writes never collide) and returns the matches it made in the halo: those belong to the
neighbouring tiles and become their seeds in the next round. Rounds repeat until no tile
sends a seed on (a receiving tile whose seeds all land on matched pixels returns at once,
without reading any image), or until ``max_rounds``, which is reported.

Each task reads its base window and the distorted window the polynomial says it needs
straight from the Zarr stores; memory per task depends on the tile size only.

The state is double-buffered: every tile has two slots, a task reads the slot of its last
finished round and writes the other, and the driver flips a tile's slot only once the
round is over. So a task that runs twice (its worker died, or the whole job was killed
and rerun) reads the same input and writes the same output: the result does not depend on
failures. With a :class:`~geocoder.pipeline.job.Job`, the round's seeds and slots are
stored at the start of every round and each tile's result when it finishes.

The module is over 500 lines because everything in it reads or writes that one store
through its layout (two slots, the compact lattice, :func:`create_state`, :func:`_read_state`):
the rounds, the every-pixel passes and the field's tiles; the kernels they run live in
:mod:`geocoder.match` and :mod:`geocoder.kernels`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from functools import partial

import dask
import dask.array as da
import numpy as np
import zarr

from ..kernels.alsc import (
    F_A11,
    F_A12,
    F_A21,
    F_A22,
    F_GAIN,
    F_OFFSET,
    F_X,
    F_Y,
    FIELDS,
    NPARAMS,
    AlscOptions,
)
from ..kernels.polynomial import PolyMap
from ..match.densify import densify_window, lattice_start, rows_between
from ..match.fill import fill_window
from ..match.grow import NFIELDS, SEED_COL, SEED_ROW, SEED_WIDTH, SEED_X, SEED_Y, UNVISITED, grow_window, seed_rows
from ..match.tiepoints import TiePoints
from ..scene import WindowReader
from ..storage import Arrays, open_array, open_group
from ..tiles import Tile, TileGrid, Window
from .bands import Bands, band_windows
from .correspond import distorted_window
from .job import Job, run_tiles

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DenseOptions:
    """Options of the dense stage.

    alsc : least-squares matching options. The default template is 51 x 7 pixels: long along
        the scan line, where the distortion is smooth, and short across it, where roll and
        pitch change from line to line (a square template of the same area averages the
        line-to-line turbulence and biases the match by 0.1-0.3 px; see the issue notes).
        Matches are accepted from a correlation of 0.6 (ALSC's own default 0.7): the other
        tests (sigma <= 0.1 px, the move, convergence) keep the blunders out, and a
        low-contrast template (dark water with a few bright specks) is still precise. On the
        nine cases of ``bench_dense_cases.py`` the matched share rises 0.0-3.3 points
        (Landsat 58.3 -> 61.0 %, coverage of its textured overlap 81.6 -> 84.4 %), the matched
        RMSE within +-0.001 px and calibration the same or nearer 1 (issue 14's note).
    halo : width (px) of the band around a tile in which it may grow into its neighbours
        (at least ``col_step``, so that the lattice reaches into the neighbours).
    step : lattice spacing of the matches (1 = every pixel).
    col_step : with ``step = 1``: the region growing (full Gauss-Newton matches, halo exchange)
        runs on every row but only on every ``col_step``-th column (global lattice; the halo
        must be at least ``col_step``); after the last round one pass per tile matches every
        pixel (``densify``). 1 = the region growing of every pixel (the seed's method as such,
        4-5x slower in the dense stage). Default 16: on the tests' real crops (S2 1024^2,
        aerial 512^2) and the demo's synthetic texture it is as accurate as full growth or
        better, covers more of the textured overlap and gives a better calibrated sigma
        (figures in the notes of issue 12).
    row_step : the region growing's lattice on every ``row_step``-th scan line only (the
        global rows ``alsc.ry + k row_step``: the first a template fits in, then every
        ``row_step``-th); the lines between start the every-pixel pass from the lattice lines on
        either side (:func:`geocoder.match.densify.rows_between`). Only with ``col_step > 1`` and
        ``densify="field"`` (:attr:`lattice_rows`); full growth and ``"step"`` match every line.
        Default 2 (measured with ``lattice_tol`` 0.005): against every line at 0.01 (2048^2 bench pair, 2
        workers, three interleaved pairs of runs) the region growing's task time 8.2 -> 5.7 s,
        the job 13.4 -> 12.0 s; on the nine simulated cases of ``bench_dense_cases.py`` the same matched RMSE
        (+-0.001 px) and coverage of the textured overlap the same or up to 0.6 points higher;
        on the real-field check (``tests/test_error_analysis.py``, S2 clean) 0.0447 -> 0.0476 px,
        calibration y 1.15 -> 1.20: a real field's line-to-line structure is what the lines
        between lose. Every 3rd line: the same on the simulated cases, 0.056 px there (issue 12's
        notes).
    fill_step_tol : largest ``(x, y)`` step (px) accepted after the one step of a pixel filled
        by ``densify="step"``.
    densify : how the pixels between the lattice columns are matched when ``col_step > 1``:
        ``"field"`` (every pixel of a tile at once, least squares from window sums on the
        distorted image resampled at the lattice's interpolation along the lines;
        :mod:`geocoder.match.densify`) or ``"step"`` (one verified Gauss-Newton step per
        pixel from its two lattice neighbours; :mod:`geocoder.match.fill`).
    lattice_tol : convergence threshold (px) of the lattice's matches when ``col_step > 1``
        (instead of ``alsc.tol``): they only start and seed the every-pixel pass, which matches
        every pixel again and decides the output. 0.01 px against 2e-4 halved the growth's CPU
        time at the same result on the tests' crops (issue 12's notes). A lattice line's small
        path dependence (which neighbour predicted a run of its matches, so which side they
        converged from) reaches the every-pixel pass through its starts, which its rounds take
        back all but a share of (a fifth in y). Between the tilings of ``tests/test_dense.py``,
        matched pixels: 0.0003 px at 0.005, 0.0028 at 0.01, 0.0092 at 0.05 (estimated pixels:
        0.0026, 0.015, 0.049; with the bilinear sample of the every-pixel pass before the
        Lanczos-3 one, 0.0146 px at 0.01). 0.01 against 0.005: the region growing 21 % less
        CPU time (three captured 1024 tiles of the 2048^2 bench pair, 4.43 -> 3.50 s), the
        nine cases of ``bench_dense_cases.py`` the same coverage (+-0.1 point) and matched RMSE
        (the same or 0.001 px lower).
    densify_iterations : resampling rounds of ``"field"``.
    densify_gradients : the design of ``"field"`` (see :func:`geocoder.kernels.fieldlsq.field_lsq`):
        ``"template"`` (default; the base template's gradients, samples on the field smoothed
        over the template) or ``"image"`` (the resampled image's slopes, each template
        linearised about its own centre; biased by the noise of the slopes on smooth texture).
    densify_tol : largest last move (px) of a pixel accepted by ``"field"``.
    densify_gap, densify_extend : how far (px) ``"field"`` interpolates the lattice along a
        scan line between two matches, and carries it past a line's first and last match, for
        the starts (:func:`geocoder.match.densify.lattice_start`; every start is verified by
        the match). Past the ends: the end match's affine for 32 px, and where the run of
        matches tells the line's slope and curvature, along its last chord as far as the
        curvature (plus twice its noise) keeps that within a quarter pixel (at most
        ``densify_extend``). 512 and 512 against 128 and 32 raised the coverage of the textured
        overlap S2 1024^2 97.7 -> 98.8 %, strong S2 2048^2 91.6 -> 95.6 %, Landsat 576^2 76.0
        -> 81.0 % at the same matched RMSE (issue 14's notes; without the noise term 99.2,
        96.0, 83.0 %: the margin is kept against a curvature small by chance). Not kept: the
        affine alone over 128 px (the rims of untextured areas matched worse, strong S2 0.052
        -> 0.062 px); holding the residual about the global polynomial (the starts then
        depend on the polynomial, which differs between tilings where it is poorly
        determined: 29 px on a pair with a flat half).
    neighbours : 4 or 8.
    max_tries : attempts per pixel from different neighbours within one task.
    max_rounds : limit of halo-exchange rounds.
    margin : extra distorted pixels read around the polynomial's prediction of a window.
    """

    alsc: AlscOptions = field(default_factory=lambda: AlscOptions(
        radius=25, radius_y=3, max_shift=0.5, min_rho=0.6, max_sigma=0.1, tol=2e-4, max_iter=30))
    halo: int = 16
    step: int = 1
    col_step: int = 16
    row_step: int = 2
    fill_step_tol: float = 0.05
    densify: str = "field"
    lattice_tol: float = 0.01
    densify_iterations: int = 2
    densify_gradients: str = "template"
    densify_tol: float = 0.1
    densify_gap: int = 512
    densify_extend: int = 512
    neighbours: int = 4
    max_tries: int = 2
    max_rounds: int = 12
    margin: int = 24

    @property
    def lattice_rows(self) -> int:
        """The lattice's row spacing: ``row_step`` with ``col_step > 1`` and ``densify="field"``, else 1."""
        return self.row_step if self.col_step > 1 and self.densify == "field" else 1

    @property
    def lattice_row0(self) -> int:
        """A global row of the lattice: the first line a template fits in (every :attr:`lattice_rows`-th from it)."""
        return self.alsc.ry if self.lattice_rows > 1 else 0

    @property
    def growth_alsc(self) -> AlscOptions:
        """The least-squares matching options of the region growing (``lattice_tol`` on a lattice)."""
        return replace(self.alsc, tol=self.lattice_tol) if self.col_step > 1 else self.alsc

    def __post_init__(self) -> None:
        if not self.lattice_tol > 0:
            raise ValueError(f"lattice_tol must be positive, got {self.lattice_tol!r}")
        if int(self.col_step) != self.col_step or self.col_step < 1:
            raise ValueError(f"col_step must be a positive integer, got {self.col_step!r}")
        if self.col_step > 1 and self.step != 1:
            raise ValueError("col_step > 1 needs step = 1")
        if int(self.row_step) != self.row_step or self.row_step < 1:
            raise ValueError(f"row_step must be a positive integer, got {self.row_step!r}")
        if max(self.col_step, self.lattice_rows) > self.halo:
            raise ValueError(f"col_step ({self.col_step}) and row_step ({self.lattice_rows}) must not exceed the halo "
                             f"({self.halo})")
        if not self.fill_step_tol > 0:
            raise ValueError(f"fill_step_tol must be positive, got {self.fill_step_tol!r}")
        if self.densify not in ("field", "step"):
            raise ValueError(f"densify must be 'field' or 'step', got {self.densify!r}")
        if int(self.densify_iterations) != self.densify_iterations or self.densify_iterations < 1:
            raise ValueError(f"densify_iterations must be a positive integer, got {self.densify_iterations!r}")
        if self.densify_gradients not in ("image", "template"):
            raise ValueError(f"densify_gradients must be 'image' or 'template', got {self.densify_gradients!r}")
        if not self.densify_tol > 0:
            raise ValueError(f"densify_tol must be positive, got {self.densify_tol!r}")
        if self.densify_gap < 0 or self.densify_extend < 0:
            raise ValueError(f"densify_gap and densify_extend must be >= 0, got {self.densify_gap}, {self.densify_extend}")


@dataclass(frozen=True)
class DenseResult:
    """Where the state is, how many rounds ran, the matches made per round, and the job's tiles."""

    store: str
    rounds: int
    converged: bool
    new_per_round: list[int]
    slots: np.ndarray
    grid: TileGrid


def create_state(path: str, shape: tuple[int, int], tile: int, lattice: int = 1) -> None:
    """Empty state store of two slots: ``fields`` (2, 12, H, W) float32 NaN and ``code`` (2, H, W) int8 -1.

    With ``lattice = k > 1`` the region growing's matches (every k-th column only) go to the
    compact arrays ``lattice`` (2, 12, H, ceil(W / k)) and ``lattice_code``, one chunk per tile
    (``tile`` a multiple of k), so its rounds read and write a k-th of the full fields.
    """
    g = zarr.open_group(path, mode="w", zarr_format=3)
    # uncompressed: a working store written and read in every round, on the job's own disk
    # (zstd cost ~2 ms of decode or encode per chunk read or written, handed to zarr's thread pool)
    create = partial(g.create_array, compressors=None)
    # one chunk per field and tile: a stage that needs a few fields decodes only those
    create("fields", shape=(2, NFIELDS, *shape), chunks=(1, 1, tile, tile), dtype="float32", fill_value=np.nan)
    create("code", shape=(2, *shape), chunks=(1, tile, tile), dtype="int8", fill_value=UNVISITED)
    if lattice > 1:
        lshape, lchunk = (shape[0], -(-shape[1] // lattice)), (tile, tile // lattice)
        # all fields of a tile in one chunk: the rounds always read and write them together
        create("lattice", shape=(2, NFIELDS, *lshape), chunks=(1, NFIELDS, *lchunk), dtype="float32",
                       fill_value=np.nan)
        create("lattice_code", shape=(2, *lshape), chunks=(1, *lchunk), dtype="int8", fill_value=UNVISITED)


def lattice_step(grid: TileGrid, opts: DenseOptions) -> int:
    """Column step of the compact lattice state (see :func:`create_state`), 1 for none.

    The lattice state is compact when the region growing runs on every ``col_step``-th
    column, the pixels between are matched by ``densify="field"``, and every tile but the
    last starts on a lattice column (its width a multiple of ``col_step``).
    """
    k = opts.col_step
    aligned = all(c % k == 0 for c in grid.cols[:-1]) and all(r == grid.rows[0] for r in grid.rows[:-1]) \
        and grid.rows[0] == grid.cols[0]
    return k if k > 1 and opts.densify == "field" and aligned else 1


def _core_columns(tile: Tile, k: int) -> tuple[slice, slice]:
    """Columns of a tile's core in the state arrays (compact for ``k > 1``) and within the core."""
    if k == 1:
        return slice(tile.col0, tile.col1), slice(None)
    return slice(tile.col0 // k, -(-tile.col1 // k)), slice(None, None, k)


def _read_core(g, tile: Tile, slot: int, k: int, what: str, *, compact: bool = False) -> np.ndarray:
    """``"code"`` (h, w) int8 or ``"fields"`` (12, h, w) float32 of a tile's core from slot ``slot``,
    at full width (UNVISITED / NaN between the lattice columns of a compact state), or as
    stored (``compact``: every ``k``-th column)."""
    stored, within = _core_columns(tile, k)
    rows = slice(tile.row0, tile.row1)
    shape = (tile.row1 - tile.row0, tile.col1 - tile.col0)
    if what == "code":
        part = g["code" if k == 1 else "lattice_code"][slot, rows, stored]
        out = np.full(shape, UNVISITED, dtype=np.int8)
    else:
        part = g["fields" if k == 1 else "lattice"][slot, :, rows, stored]
        out = np.full((NFIELDS, *shape), np.nan, dtype=np.float32)
    if k == 1 or compact:
        return part
    out[..., within] = part
    return out


def _write_core(g, tile: Tile, slot: int, k: int, values: np.ndarray, code: np.ndarray,
                fields: tuple[int, ...] | None = None) -> None:
    """Write a tile's core (``values`` (12, h, w') or the ``fields`` given, ``code`` (h, w'), w'
    the stored columns) to slot ``slot``."""
    stored, _ = _core_columns(tile, k)
    rows = slice(tile.row0, tile.row1)
    g["fields" if k == 1 else "lattice"][slot, slice(None) if fields is None else list(fields), rows, stored] = values
    g["code" if k == 1 else "lattice_code"][slot, rows, stored] = code


def _param_window(shape: tuple[int, int], k: int, wc0: int) -> np.ndarray:
    """NaN ALSC fields (h, w', 12) float64 of a window whose first column is the global ``wc0``:
    every column (``k = 1``) or the global lattice columns (multiples of ``k``) only."""
    h, w = shape
    return np.full((h, -(-(w - (-wc0 % k)) // k), NFIELDS), np.nan)


def seeds_from_tiepoints(tp: TiePoints, mapping: PolyMap) -> np.ndarray:
    """Seed rows (:data:`geocoder.match.grow.SEED_COLUMNS`) in global frames.

    The affine starts from the polynomial's Jacobian, the radiometry from identity.
    """
    tp = tp.select(tp.inlier)
    jac = mapping.jacobian(tp.base_x, tp.base_y)
    start = np.empty((len(tp), NPARAMS))
    start[:, F_X], start[:, F_Y] = tp.dist_x, tp.dist_y
    start[:, F_A11], start[:, F_A12], start[:, F_A21], start[:, F_A22] = jac[:, 0, 0], jac[:, 0, 1], jac[:, 1, 0], jac[:, 1, 1]
    start[:, F_OFFSET], start[:, F_GAIN] = 0.0, 1.0
    return seed_rows(tp.base_y, tp.base_x, start)


def _route(seeds: np.ndarray, grid: TileGrid, exclude: str | None = None) -> dict[str, np.ndarray]:
    """Hand seeds to the tiles whose core holds them."""
    if seeds.size == 0:
        return {}
    return {key: seeds[i] for key, i in grid.route(seeds[:, SEED_COL], seeds[:, SEED_ROW]).items() if key != exclude}


def _grow_task(tile: Tile, seeds: np.ndarray, shape, base_reader: WindowReader, dist_reader: WindowReader,
               band: int, dist_band: int, state: str, slot: int, mapping: PolyMap, opts: DenseOptions, k: int = 1,
               bands: Bands | None = None):
    """Grow one tile from ``seeds``: reads slot ``slot`` of its core, writes slot ``1 - slot``
    (of the compact lattice state when ``k > 1``, see :func:`create_state`).

    Returns ``(new matches, outgoing halo seeds, whether the other slot was written)``.
    """
    h, w = shape
    g = Arrays(state, mode="r+")
    core_code = _read_core(g, tile, slot, k, "code")
    rows = seeds[:, SEED_ROW].astype(np.int64) - tile.row0
    cols = seeds[:, SEED_COL].astype(np.int64) - tile.col0
    incore = (rows >= 0) & (rows < core_code.shape[0]) & (cols >= 0) & (cols < core_code.shape[1])
    useful = ~incore.copy()
    useful[incore] = core_code[rows[incore], cols[incore]] != 0
    if not useful.any():
        return 0, np.empty((0, SEED_WIDTH)), False
    # growth region (global), and the base window around it with the template margin
    rr0, rr1, rc0, rc1 = tile.window(opts.halo).clip(h, w)
    pad = max(opts.alsc.radius, opts.alsc.ry) + 2
    wr0, wc0 = rr0 - pad, rc0 - pad
    dwin = distorted_window(Tile(0, 0, rr0, rr1, rc0, rc1), mapping, opts.margin + 2 * max(opts.alsc.radius, opts.alsc.ry))
    dr0, dc0 = dwin[0], dwin[2]
    base, dist = band_windows(base_reader.read(wr0, rr1 + pad, wc0, rc1 + pad), dist_reader.read(*dwin), band, dist_band,
                          bands)
    # window state: the core's earlier matches, nothing in the halo; ``params`` holds the
    # lattice's columns only when the state does (every k-th, from the core's first)
    params, p0, (cr, cc) = _param_window(base.shape[-2:], k, wc0), -wc0 % k, (tile.row0 - wr0, tile.col0 - wc0)
    code = np.full(base.shape[-2:], UNVISITED, dtype=np.int8)
    csl = (slice(cr, cr + tile.row1 - tile.row0), slice(cc, cc + tile.col1 - tile.col0))
    stored = np.moveaxis(_read_core(g, tile, slot, k, "fields", compact=True), 0, -1)
    pc0 = (cc - p0) // k
    core = params[cr : cr + stored.shape[0], pc0 : pc0 + stored.shape[1]]  # a view: filled in place
    core[:] = stored
    xs = (tile.col0 + k * np.arange(stored.shape[1]))[None, :] - dc0
    ys = np.arange(tile.row0, tile.row1)[:, None] - dr0
    core[..., 0] += xs  # stored as displacement, used as distorted-window position
    core[..., 1] += ys
    code[csl] = core_code
    local = seeds[useful].copy()
    local[:, SEED_ROW] -= wr0
    local[:, SEED_COL] -= wc0
    local[:, SEED_X] -= dc0
    local[:, SEED_Y] -= dr0
    region = (rr0 - wr0, rr1 - wr0, rc0 - wc0, rc1 - wc0)
    new = grow_window(base, dist, local, params, code, region, options=opts.growth_alsc, step=opts.step,
                      lattice_origin=((opts.lattice_row0 - wr0) % (opts.step * opts.lattice_rows),
                                      -wc0 % (opts.step * opts.col_step)),
                      neighbours=opts.neighbours, max_tries=opts.max_tries, col_step=opts.col_step,
                      row_step=opts.lattice_rows, param_stride=k)
    if new == 0:
        return 0, np.empty((0, SEED_WIDTH)), False
    _, within = _core_columns(tile, k)
    out = np.moveaxis(core, -1, 0).astype(np.float32)
    out[0] = core[..., 0] - xs
    out[1] = core[..., 1] - ys
    _write_core(g, tile, 1 - slot, k, out, code[csl][:, within])
    # matches made in the halo are the neighbours' seeds for the next round
    halo = code == 0
    halo[csl] = False
    hr, hc = np.nonzero(halo)
    start = params[hr, (hc - p0) // k, :NPARAMS]
    start[:, F_X] += dc0
    start[:, F_Y] += dr0
    outgoing = seed_rows(hr + wr0, hc + wc0, start)
    return new, outgoing, True


def grow_tiles(
    base_reader: WindowReader,
    dist_reader: WindowReader,
    grid: TileGrid,
    seeds: np.ndarray,
    mapping: PolyMap,
    state: str,
    *,
    band: int = 0,
    dist_band: int = 0,
    opts: DenseOptions = DenseOptions(),
    job: Job | None = None,
    bands: Bands | None = None,
) -> DenseResult:
    """Run the halo-exchange rounds; the matches end up in the ``state`` store.

    With a ``job``, a rerun continues from the round (and the tiles of it) where an
    earlier run stopped. With ``bands``, every match is on those bands at once (not with
    ``densify="step"``); ``band`` and ``dist_band`` are then not used.
    """
    if bands is not None and opts.col_step > 1 and opts.densify != "field":
        raise ValueError("matching several bands needs densify='field'")
    shape = (grid.height, grid.width)
    tiles = {t.key: t for t in grid}
    lat = lattice_step(grid, opts)
    start = next((r for r in range(opts.max_rounds, -1, -1) if job is not None and job.done(f"dense-round-{r}")), None)
    if start is None:
        create_state(state, shape, grid.rows[0], lat)
        start, pending, slots, per_round = 0, _route(seeds, grid), {k: 0 for k in tiles}, []
        if job is not None:
            job.save("dense-round-0", (pending, slots, per_round))
    else:
        pending, slots, per_round = job.load(f"dense-round-{start}")
    rounds = opts.max_rounds
    for rnd in range(start, opts.max_rounds):
        if not pending:
            rounds = rnd
            break
        keys = sorted(pending)
        token = dask.base.tokenize(state, slots, rnd)
        tasks = {
            k: dask.delayed(_grow_task, pure=False)(
                tiles[k], pending[k], shape, base_reader, dist_reader, band, dist_band, state, slots[k], mapping, opts,
                lat, bands, dask_key_name=f"grow-{k}-r{rnd}-{token}",
            )
            for k in keys
        }
        results = run_tiles(job, f"dense-r{rnd}", tasks, phase=f"dense matching (round {rnd + 1})")
        per_round = [*per_round, int(sum(r[0] for r in results.values()))]
        log.info("dense round %d: %d tiles, %d new matches", rnd, len(keys), per_round[-1])
        nxt: dict[str, list[np.ndarray]] = {}
        slots = dict(slots)
        for k in keys:
            _, outgoing, wrote = results[k]
            if wrote:
                slots[k] = 1 - slots[k]
            for dest, s in _route(outgoing, grid, exclude=k).items():
                nxt.setdefault(dest, []).append(s)
        pending = {k: np.concatenate(v) for k, v in nxt.items()}
        if job is not None:
            job.save(f"dense-round-{rnd + 1}", (pending, slots, per_round))
    if opts.col_step > 1:
        task, name, phase = ((partial(_densify_task, lattice=lat, bands=bands), "densify", "dense matching (every pixel)")
                             if opts.densify == "field" else (_fill_task, "fill", "dense matching (fill)"))
        slots = _tile_pass(task, name, phase, base_reader, dist_reader, grid, mapping, state, slots, band=band,
                           dist_band=dist_band, opts=opts, job=job)
    return DenseResult(state, rounds, not pending, per_round, _slot_grid(grid, slots), grid)


def _fill_task(tile: Tile, shape, base_reader: WindowReader, dist_reader: WindowReader, band: int, dist_band: int,
               state: str, slots: np.ndarray, grid: TileGrid, mapping: PolyMap, opts: DenseOptions):
    """Fill the columns between the lattice columns of one tile's core.

    Reads the lattice matches of the core and of ``col_step`` columns on either side (every
    tile from its current slot), writes the core to the other slot of the tile. Returns
    ``(new matches, the slot written or None)``; a tile with nothing to fill returns at
    once, without reading any image.
    """
    h, w = shape
    k = opts.col_step
    _, _, sc0, sc1 = tile.window().grow(0, k).clip(h, w)
    f, scode = _read_state(state, slots, grid, tile.row0, tile.row1, sc0, sc1, fields=tuple(range(NFIELDS)))
    cols = np.arange(sc0, sc1)
    lattice = (cols % k == 0)[None, :]
    matched = (scode == 0) & lattice
    core = slice(tile.col0 - sc0, tile.col1 - sc0)
    # a core pixel between lattice columns can be filled if a lattice neighbour matched
    n = scode.shape[1]
    cl = cols - cols % k - sc0
    cr = cl + k
    left = matched[:, np.clip(cl, 0, n - 1)] & (cl >= 0)[None, :]
    right = matched[:, np.clip(cr, 0, n - 1)] & (cr < n)[None, :]
    todo = (left | right) & ~lattice & (scode != 0)
    if not todo[:, core].any():
        return 0, None
    pad = max(opts.alsc.radius, opts.alsc.ry) + 2
    wr0, wc0 = tile.row0 - pad, tile.col0 - pad
    base = base_reader.read(wr0, tile.row1 + pad, wc0, tile.col1 + pad)[band]
    dwin = distorted_window(tile, mapping, opts.margin + 2 * max(opts.alsc.radius, opts.alsc.ry))
    dr0, dc0 = dwin[0], dwin[2]
    dist = dist_reader.read(*dwin)[dist_band]
    params = np.full((*base.shape, NFIELDS), np.nan)
    code = np.full(base.shape, UNVISITED, dtype=np.int8)
    ssl = (slice(tile.row0 - wr0, tile.row1 - wr0), slice(sc0 - wc0, sc1 - wc0))
    win = params[ssl]
    win[:] = np.moveaxis(f, 0, -1)
    win[..., 0] += (cols - dc0)[None, :]  # stored as displacement, used as distorted-window position
    win[..., 1] += (np.arange(tile.row0, tile.row1) - dr0)[:, None]
    code[ssl] = scode
    region = (tile.row0 - wr0, tile.row1 - wr0, tile.col0 - wc0, tile.col1 - wc0)
    new = fill_window(base, dist, params, code, region, options=opts.alsc, col_step=k,
                      col_origin=(-wc0) % k, step_tol=opts.fill_step_tol)
    csl = (slice(region[0], region[1]), slice(region[2], region[3]))
    out = np.moveaxis(params[csl], -1, 0).astype(np.float32)
    out[0] -= (np.arange(tile.col0, tile.col1) - dc0)[None, :]
    out[1] -= (np.arange(tile.row0, tile.row1) - dr0)[:, None]
    slot = int(slots[tile.iy, tile.ix])
    g = Arrays(state, mode="r+")
    g["fields"][1 - slot, :, tile.row0 : tile.row1, tile.col0 : tile.col1] = out
    g["code"][1 - slot, tile.row0 : tile.row1, tile.col0 : tile.col1] = code[csl]
    return new, 1 - slot


def _densify_task(tile: Tile, shape, base_reader: WindowReader, dist_reader: WindowReader, band: int, dist_band: int,
                  state: str, slots: np.ndarray, grid: TileGrid, mapping: PolyMap, opts: DenseOptions, lattice: int = 1,
                  bands: Bands | None = None):
    """Match every pixel of one tile's core from the lattice (:mod:`geocoder.match.densify`).

    Reads the lattice matches of the core grown by the templates of every resampling round
    (and by ``densify_gap`` columns more for the interpolation along the lines), every tile
    from its current slot (of the compact state when ``lattice > 1``: then the core is
    written to slot 0 of the full-width fields, else to the other slot), every pixel from
    the dense pass (a lattice match that it rejects is rejected). Returns ``(matches, the
    slot written or None)``.
    """
    h, w = shape
    k, n = opts.col_step, opts.densify_iterations
    rx, ry = opts.alsc.radius, opts.alsc.ry
    # every round reaches one template half-size further (two with the template's gradients), plus
    # a pixel for the template's central differences
    reach_rounds = n * (2 if opts.densify_gradients == "template" else 1)
    bwin = tile.window().grow(reach_rounds * ry + 1, reach_rounds * rx + 1).clip(h, w)
    br0, br1, bc0, bc1 = bwin
    # the lattice rows on either side of the window's first and last lines, for their starts
    rstep = opts.lattice_rows
    lr0, lr1, sc0, sc1 = bwin.grow(rstep - 1, max(opts.densify_gap, opts.densify_extend)).clip(h, w)
    f, scode = _read_state(state, slots, grid, lr0, lr1, sc0, sc1, fields=_START_FIELDS, lattice=lattice)
    cols = np.arange(sc0, sc1)
    matched = (scode == 0) & (cols % k == 0)[None, :]
    if not matched[max(tile.row0 - rstep + 1, lr0) - lr0 : tile.row1 + rstep - 1 - lr0].any():
        return 0, None
    x0, y0, started = lattice_start(f[0] + cols[None, :], f[1] + np.arange(lr0, lr1)[:, None], f[2], f[3], matched,
                                    max_gap=opts.densify_gap, max_extend=opts.densify_extend, sigma_x=f[4],
                                    sigma_y=f[5])
    x0, y0, started = rows_between(x0, y0, started, lr0, rstep, h, origin=opts.lattice_row0)
    wsl = (slice(br0 - lr0, br1 - lr0), slice(bc0 - sc0, bc1 - sc0))
    x0, y0, started = x0[wsl], y0[wsl], started[wsl]
    dwin = distorted_window(Tile(0, 0, br0, br1, bc0, bc1), mapping, opts.margin)
    dr0, dc0 = dwin[0], dwin[2]
    base, dist = band_windows(base_reader.read(br0, br1, bc0, bc1), dist_reader.read(*dwin), band, dist_band, bands)
    region = (tile.row0 - br0, tile.row1 - br0, tile.col0 - bc0, tile.col1 - bc0)
    res = densify_window(base, dist, x0 - dc0, y0 - dr0, started, region, options=opts.alsc,
                         iterations=n, tol=opts.densify_tol, gradients=opts.densify_gradients)
    # only what the dense field reads from here on (:data:`_OUT_FIELDS`); the other fields stay NaN
    out = np.stack([res.x + dc0 - np.arange(tile.col0, tile.col1)[None, :],
                    res.y + dr0 - np.arange(tile.row0, tile.row1)[:, None],
                    res.sigma_x, res.sigma_y, res.rho]).astype(np.float32)
    code = res.code
    slot = 0 if lattice > 1 else 1 - int(slots[tile.iy, tile.ix])
    _write_core(Arrays(state, mode="r+"), tile, slot, 1, out, code, fields=_OUT_FIELDS)
    return int((code == 0).sum()), slot


def _tile_pass(task, name: str, phase: str, base_reader: WindowReader, dist_reader: WindowReader, grid: TileGrid,
               mapping: PolyMap, state: str, slots: dict[str, int], *, band: int, dist_band: int, opts: DenseOptions,
               job: Job | None) -> dict[str, int]:
    """One pass of ``task`` (:func:`_densify_task` or :func:`_fill_task`) over every tile after
    the last round; returns the new slots (of the tiles that wrote, the slot they wrote)."""
    if job is not None and job.done(f"dense-{name}-done"):
        return job.load(f"dense-{name}-done")
    shape = (grid.height, grid.width)
    tiles = {t.key: t for t in grid}
    sgrid = _slot_grid(grid, slots)
    token = dask.base.tokenize(state, slots, name, opts)
    tasks = {
        k: dask.delayed(task, pure=False)(
            tiles[k], shape, base_reader, dist_reader, band, dist_band, state, sgrid, grid, mapping, opts,
            dask_key_name=f"{name}-{k}-{token}",
        )
        for k in sorted(tiles)
    }
    results = run_tiles(job, f"dense-{name}", tasks, phase=phase)
    slots = dict(slots)
    for k, (_, wrote) in results.items():
        if wrote is not None:
            slots[k] = wrote
    log.info("dense %s: %d matches", name, int(sum(r[0] for r in results.values())))
    if job is not None:
        job.save(f"dense-{name}-done", slots)
    return slots


def _slot_grid(grid: TileGrid, slots: dict[str, int]) -> np.ndarray:
    out = np.zeros((len(grid.rows), len(grid.cols)), dtype=np.int8)
    for t in grid:
        out[t.iy, t.ix] = slots[t.key]
    return out


_OUT_FIELDS = tuple(FIELDS.index(n) for n in ("x", "y", "sigma_x", "sigma_y", "rho"))
_START_FIELDS = tuple(FIELDS.index(n) for n in ("x", "y", "a11", "a21", "sigma_x", "sigma_y"))


def _read_state(state: str, slots: np.ndarray, grid: TileGrid, r0: int, r1: int, c0: int, c1: int,
                fields: tuple[int, ...] = _OUT_FIELDS, lattice: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Fields (default ``x, y, sigma_x, sigma_y, rho``: (5, h, w)) and ``code`` (h, w) of a
    window of the state, every tile's part from its current slot; from the compact lattice
    state when ``lattice > 1`` (NaN and UNVISITED between its columns)."""
    g = Arrays(state, mode="r")
    farr, carr = ("fields", "code") if lattice == 1 else ("lattice", "lattice_code")
    redges = np.r_[0, np.cumsum(grid.rows)]
    cedges = np.r_[0, np.cumsum(grid.cols)]
    out = np.full((len(fields), r1 - r0, c1 - c0), np.nan, dtype=np.float32)
    code = np.full((r1 - r0, c1 - c0), UNVISITED, dtype=np.int8)
    # the stored columns of the window: every column, or the lattice columns in compact form
    sa0, sb0 = (c0, c1) if lattice == 1 else (-(-c0 // lattice), -(-c1 // lattice))
    if sa0 >= sb0:
        return out, code
    iys = [iy for iy in range(len(grid.rows)) if max(r0, redges[iy]) < min(r1, redges[iy + 1])]
    ixs = [ix for ix in range(len(grid.cols)) if max(c0, cedges[ix]) < min(c1, cedges[ix + 1])]
    used = sorted({int(slots[iy, ix]) for iy in iys for ix in ixs})
    # one read of the whole window per slot in use (a read per tile and array cost more than the data)
    stored = {s: (g[farr][s, list(fields), r0:r1, sa0:sb0], g[carr][s, r0:r1, sa0:sb0]) for s in used}
    for iy in iys:
        ra, rb = max(r0, int(redges[iy])) - r0, min(r1, int(redges[iy + 1])) - r0
        for ix in ixs:
            a, b = max(c0, int(cedges[ix])), min(c1, int(cedges[ix + 1]))
            sa, sb = (a, b) if lattice == 1 else (-(-a // lattice), -(-b // lattice))
            if sa >= sb:
                continue
            f, cd = stored[int(slots[iy, ix])]
            part = slice(sa - sa0, sb - sa0)
            tcols = slice(sa * lattice - c0, (sb - 1) * lattice - c0 + 1, lattice)
            out[:, ra:rb, tcols] = f[:, ra:rb, part]
            code[ra:rb, tcols] = cd[ra:rb, part]
    return out, code


def _dense_block(block_info=None, *, state: str, slots: np.ndarray, grid: TileGrid, postfilter_options) -> np.ndarray:
    from ..quality.postfilter import halo, postfilter
    from ..status import Status

    (r0, r1), (c0, c1) = block_info[None]["array-location"][1:]
    pad = halo(postfilter_options)  # the post-filter works along scan lines only
    _, _, w0, w1 = Window(r0, r1, c0, c1).grow(0, pad).clip(grid.height, grid.width)
    f, code = _read_state(state, slots, grid, r0, r1, w0, w1)
    matched = code == 0
    status = np.where(matched, Status.MATCHED, Status.NO_TEXTURE).astype(np.uint8)
    dx, dy, status = postfilter(np.where(matched, f[0], np.nan), np.where(matched, f[1], np.nan), status, options=postfilter_options)
    core = slice(c0 - w0, c0 - w0 + (c1 - c0))
    sl = (slice(None), core)
    keep = status[sl] == Status.MATCHED
    return np.stack([
        dx[sl], dy[sl], status[sl].astype(np.float32),
        np.where(keep, f[2][sl], np.nan), np.where(keep, f[3][sl], np.nan), np.where(keep, f[4][sl], np.nan),
    ]).astype(np.float32)


def dense_field(result: DenseResult, fallback: tuple[da.Array, da.Array], postfilter_options, *, store: bool = False,
                job: Job | None = None, line_sums_of: PolyMap | None = None) -> dict:
    """Final displacement and quality arrays from the state store (lazy).

    Matched pixels go through the scan-line post-filter (blunders removed, short holes
    filled along rows, every filled pixel flagged); pixels left without a match take the
    polynomial's displacement (``fallback``) and keep their flag. One task per tile reads
    its rows of the state, with the post-filter's halo along them, straight from the store
    (every tile from its current slot), so a worker holds one tile's window whatever the
    scene size. With ``store``, those tasks run now and write their tiles into the state
    store (array ``field``, through ``job`` when given), and the arrays returned read them:
    for callers that compute the field more than once (the line estimates, then the output).
    With ``store`` and ``line_sums_of`` (the polynomial ``fallback`` comes from), each of those
    tasks also returns its tile's row sums (:func:`geocoder.pipeline.lines.tile_sums`, with the
    polynomial computed in the task), returned side by side as ``"line_sums"`` for
    :func:`geocoder.pipeline.lines.row_corrections`: no second pass over the field (which, as one
    graph of every tile, held memory that grew with the scene: 598 -> 914 MiB per worker at 8192²).
    """
    from ..status import Status

    grid = result.grid
    if fallback[0].chunks != grid.chunks:
        raise ValueError(f"the fallback's chunks {fallback[0].chunks} are not the dense tiles {grid.chunks}")
    stack = da.map_blocks(
        _dense_block, chunks=((6,), *fallback[0].chunks), dtype=np.float32,
        state=result.store, slots=result.slots, grid=grid, postfilter_options=postfilter_options,
        name=f"dense-field-{dask.base.tokenize(result.store, result.slots, postfilter_options)}",
    )
    sums = None
    if store:
        stack, sums = _stored(stack, result.store, grid, job, line_sums_of)
    dx, dy, status = stack[0], stack[1], stack[2].astype(np.uint8)
    good = (status == Status.MATCHED) | (status == Status.FILLED)
    return {
        "dx": da.where(good, dx, fallback[0]).astype(np.float32),
        "dy": da.where(good, dy, fallback[1]).astype(np.float32),
        "status": status,
        "sigma_x": stack[3],
        "sigma_y": stack[4],
        "correlation": stack[5],
        **({"line_sums": sums} if sums is not None else {}),
    }


def _store_block(state: str, window: tuple[int, int, int, int], block: np.ndarray, mapping: PolyMap | None = None,
                 shape: tuple[int, int] = (0, 0)) -> np.ndarray | None:
    from .lines import field_window, tile_sums

    r0, r1, c0, c1 = window
    open_array(state, "field", mode="r+")[:, r0:r1, c0:c1] = block
    if mapping is None:
        return None
    # the row sums of the field as dense_field returns it: the polynomial where not usable
    dx, dy, px, py, status, _ = field_window(block, mapping, (r0, r1), (c0, c1))
    return tile_sums(dx, dy, px, py, status, block[3], block[4], row0=r0, col0=c0, shape=shape)


def _stored(stack: da.Array, state: str, grid: TileGrid, job: Job | None,
            mapping: PolyMap | None = None) -> tuple[da.Array, np.ndarray | None]:
    """Write ``stack`` (6, H, W) tile by tile into the array ``field`` of the state store; the
    same array read back lazily, in the same chunks, and with ``mapping`` the tiles' row sums
    side by side, shape (n, H, tile columns)."""
    g = open_group(state, mode="r+")
    if "field" not in g:
        g.create_array("field", shape=stack.shape, chunks=(stack.shape[0], grid.rows[0], grid.cols[0]), dtype="float32",
                       fill_value=np.nan, compressors=None)
    blocks = stack.to_delayed(optimize_graph=False)
    token = "" if mapping is None else "-" + dask.base.tokenize(mapping.to_dict())
    tasks = {t.key: dask.delayed(_store_block, pure=True)(state, (t.row0, t.row1, t.col0, t.col1), blocks[0, t.iy, t.ix],
                                                          mapping, (grid.height, grid.width),
                                                          dask_key_name=f"dense-field-store-{t.key}-{stack.name}{token}")
             for t in grid}
    done = run_tiles(job, "dense-field" if mapping is None else "dense-field-sums", tasks, phase="dense field (post-filter)")
    sums = None
    if mapping is not None:
        sums = np.zeros((next(iter(done.values())).shape[0], grid.height, len(grid.cols)))
        for t in grid:
            sums[:, t.row0:t.row1, t.ix] = done[t.key][..., 0]
    return da.from_zarr(g["field"], chunks=stack.chunks, name=f"dense-field-stored-{stack.name}"), sums
