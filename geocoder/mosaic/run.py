"""``mosaic(scenes, reference=...)``: many overlapping scenes -> one block adjustment -> one mosaic.

1. Every scene and the reference are ingested to Zarr (tile-parallel), inside the job directory.
2. Every scene is matched against the reference (the registration's coarse alignment,
   Foerstner points and robust correspondence, tile-parallel): its footprint, and control
   points for the scenes allowed to have them. A scene not found there is matched against
   the placed scenes it may overlap, its mapping chained through theirs, round after round
   while one places a scene (:mod:`geocoder.mosaic.placement`); it has no control points.
3. Every pair of scenes whose footprints overlap is matched the same way: tie points.
   Steps 2 and 3 run as a few rounds for all pairs at once (:mod:`geocoder.mosaic.matching`):
   the interest points of every scene in one stage, then per batch one stage each for the
   coarse alignments and the correspondence passes, one task per base tile of every pair.
4. The block (one :class:`~geocoder.adjust.models.MapPolynomial` per scene) is adjusted on
   one node with robust re-weighting; scenes tied to no control are reported and left out.
5. The output grid (the reference's CRS and pixel, the union of the footprints) is written one
   task per tile: each task maps its pixels into every scene through the adjusted models,
   samples the ORIGINAL scenes once, and blends them across seams, feathered; ``source`` says
   which scene each pixel comes from. The seams are nearest each scene's centre
   (``seams="centre"``) or, by default, cut on a coarse grid of the output along the least
   grey-value difference of each overlapping pair (:mod:`geocoder.mosaic.seamplan`, one task per
   coarse window, then the cut on one node; every output tile reads its window of the label map).
6. The summary keeps, per scene, the adjustment's residuals (binned) and precision and its
   footprint, and per pair the seam's length, grey-value step and tie-point mismatch: what
   :func:`geocoder.mosaic.report.write_report` draws.

This module is the job's driver, :func:`mosaic`, one function whose stages read top to bottom
(hence its length); what each stage computes lives beside it: the output grid and tiles in
:mod:`~geocoder.mosaic.output`, the summary in :mod:`~geocoder.mosaic.summary`, the check points
in :mod:`~geocoder.mosaic.checkpoints`, the radiometric balance in :mod:`~geocoder.mosaic.balance`,
a mosaic without a reference in :mod:`~geocoder.mosaic.georef`.
"""

from __future__ import annotations

import contextvars
import json
import logging
import math
import os
import tempfile
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import replace

import dask
import numpy as np
import xarray as xr
from affine import Affine

from .. import progress, storage
from .._version import __version__
from ..adjust.models import RPC
from ..cog import to_cog
from ..errors import GeocoderError, InputError
from ..geometry import pixel_to_world
from ..kernels.interest import InterestPoints
from ..kernels.polynomial import fit_polymap
from ..multiscales import write_overviews
from ..options import get_option
from ..outputs import check_output, commit_output
from ..pipeline.coarse import georeference_prior
from ..pipeline.job import Job, JobRun, fingerprint, input_identity
from ..pipeline.register import RegisterOptions, _Timer, ingest_all, open_job
from ..runtime import dask_client
from ..scene import WindowReader, open_scene, scene_transform
from .balance import balance_block
from .block import POINT_COLUMNS, Matches, build_problem, connected_scenes, point_table, solve
from .checkpoints import check_residuals, given_residuals, withhold
from .control import DEFAULT_SIGMA_PX, read_control
from .dense_neighbours import refine_by_neighbours
from .diagnostics import footprint_outline
from .georef import (
    GEOREFERENCE_SIGMA_PX,
    georeference_control,
    georeference_mappings,
    virtual_reference,
)
from .heights import MapDEM, ref_to_scene_prior
from .layers import scene_uncertainty
from .matching import PairSpec, match_pairs, scene_points
from .outgrid import Reprojected
from .output import (
    footprint_box,
    mosaic_tile,
    output_crs,
    output_grid,
    scene_to_map,
    shifted,
    store_attrs,
    through_map,
)
from .placement import Placement, affine_between, footprint_from_model, overlap_fraction, place_by_neighbours
from .refine import refine_scene
from .seamplan import plan_seams
from .sensors import KINDS, scene_sensor, sensor_model
from .summary import MosaicSummary, adjustment_figures, point_sigma, seam_figures

log = logging.getLogger("geocoder")


def mosaic(
    scenes: list,
    *,
    reference=None,
    out: str | os.PathLike | None = None,
    order: int = 2,
    tile: int | None = None,
    output_tile: int | None = None,
    control_scenes: list[int] | None = None,
    check_points: float = 0.0,
    control: str | os.PathLike | None = None,
    resolution: float | None = None,
    crs=None,
    feather: float = 8.0,
    seams: str = "least-cost",
    resampling: str = "bilinear",
    balance: bool = True,
    client=None,
    scheduler: str | None = None,
    overwrite: bool = False,
    cog: str | os.PathLike | None = None,
    dense: bool | str = False,
    model: str = "polynomial",
    dem: str | os.PathLike | None = None,
    report: str | os.PathLike | None = None,
    resume: bool = True,
    show_progress=None,
    georeference_sigma: float = GEOREFERENCE_SIGMA_PX,
) -> xr.Dataset:
    """Adjust overlapping scenes as one block on a reference and write one seamless mosaic.

    Parameters
    ----------
    scenes : list of str, PathLike
        GeoTIFF/COG/Zarr scenes. A georeference is not needed: each is found on the
        reference, or, where the reference cannot find it (the scene small next to it, the
        reference untextured, cloudy or nodata there, or the scene partly outside it), on the
        scenes already placed that it overlaps: tried against those its georeference or RPCs
        say it overlaps, or against every placed scene if it carries neither. Its mapping to
        the reference is chained through that scene's (``summary["placed"]``: ``"reference"``,
        ``"via scene k"`` or ``"not placed"``); it has no control points of its own, the block
        adjustment carries it by its tie points. A scene found nowhere is reported in
        ``summary["left_out"]`` and left out.
    reference : str or PathLike, optional
        Orthoimage: the source of control points, the CRS of the scenes' models, and the
        output's CRS and pixel unless ``crs`` or ``resolution`` say otherwise. Without it
        (:mod:`geocoder.mosaic.georef`) the georeferenced scenes (at least one, all in one
        CRS) set the frame: the block is adjusted on a north-up grid of that CRS at their
        finest pixel (the output's grid unless ``crs`` or ``resolution`` say otherwise), each
        of them placed by its georeference, the others through their neighbours, all tied
        by tie points, and controlled by the ``control`` CSV or, without one, by the
        georeferences (see ``georeference_sigma``); ``dense`` then needs a reference and is
        refused, and the radiometric balance ties the scenes to each other only.
    out : str or PathLike, optional
        Zarr store to write (atomically; output safety as in :func:`geocoder.register`).
        Without it the mosaic is computed into memory.
    order : int
        Polynomial order of every scene's model (1-3).
    tile : int, optional
        Tile of all tile-parallel stages and of the output (a multiple of 64); default
        :func:`geocoder.get_option` ``("tile")`` (512 unless set).
    output_tile : int, optional
        Tile (and chunk) of the output grid, default ``tile``. The mosaic's pixels do not
        depend on it (to rounding): the seams are decided on a coarse grid, not per tile.
    control_scenes : list of int, optional
        Scenes whose reference matches serve as control points (default all); the others
        are placed by tie points only (sparse control). The ``control`` CSV's points count
        whatever this says: ``control_scenes=[]`` with a CSV is control given by hand only.
    check_points : float
        Share of every control scene's control points withheld from the adjustment as check
        points (every n-th; 0: none): their residuals through the adjusted models are the
        summary's ``check_rmse_px``, an accuracy the adjustment did not see. The ``control``
        CSV's points are withheld the same way, scene by scene.
    control : str or PathLike, optional
        Ground control points measured by hand: a CSV with a header and the columns
        ``scene`` (0-based index in ``scenes``, or the scene's file name), ``col``, ``row``
        (pixel in that scene, pixel centres at integers: the top-left pixel's centre is
        ``0, 0``), ``x``, ``y`` (map coordinates in the reference's CRS), optionally
        ``sigma`` (standard deviation of ``x`` and ``y``, map units; default half the
        reference's pixel) and ``id``. Each point is a control point of the block adjustment
        beside the reference's matches (the scene pixel observed with a precision of 0.3 px,
        :mod:`geocoder.mosaic.control`). A malformed file raises
        :class:`~geocoder.errors.InputError` naming the file, line and column before any
        work. The summary's ``given_points`` and ``given_rmse_px`` report them.
    resolution : float, optional
        The output's pixel size, in units of its CRS. Default: the reference's pixel grid
        itself. Given (or with ``crs``), the output is a north-up grid of square pixels
        aligned to multiples of ``resolution`` (pixel edges at ``k * resolution``), covering
        the scenes' footprints as the default does.
    crs : str, int or pyproj.CRS, optional
        The output's CRS (``"EPSG:32634"``, ``3857``, WKT...); default the reference's. The
        scenes' models stay in the reference's CRS: every output pixel is mapped there
        exactly (pyproj, per pixel, in its tile's task). Without ``resolution``, the pixel is
        the reference's pixel size measured in ``crs`` at the block's centre. With ``dense``,
        the fields (on the reference's grid) are sampled where each output pixel falls on it
        (bilinear, :func:`geocoder.mosaic.layers.sample_field`).
    feather : float
        Width of the blend across a seam, in output pixels.
    seams : {"least-cost", "centre"}
        Where the seams run. ``"centre"``: every pixel from the scene that sees it nearest
        its centre. ``"least-cost"``: that seam, then moved within a corridor around it onto
        the cut of least grey-value difference between the two scenes
        (:mod:`geocoder.mosaic.seams`), decided on a coarse grid of the output (cells of 8
        output pixels or more) and feathered across the label boundary in every tile.
    resampling : str
        Interpolator of the single resampling of every scene.
    balance : bool
        Radiometric balance: a gain and offset per scene and band, fitted to the reference's
        grey values at the control points and to each other's at the tie points.
    client, scheduler
        Where to run (as :func:`geocoder.register`).
    overwrite : bool
        Replace an existing ``out`` (and ``cog``) that geocoder wrote.
    cog : str or PathLike, optional
        Also write the mosaic as a Cloud-Optimized GeoTIFF (tile-parallel, with overviews;
        :func:`geocoder.cog.to_cog`).
    dense : bool
        Dense refinement: every control scene is matched pixel by pixel against the reference
        (the registration's dense stage, seeded by its control points, predicted by its
        adjusted model); where a pixel is matched or filled, the mosaic takes it from there
        instead of from the model (the line-to-line turbulence of airborne scanners, which
        no polynomial follows). Then, in rounds, every scene without control (or whose
        refinement failed) that shares tie points with refined scenes is matched the same way
        against those neighbours, brought onto the reference grid through their refined
        positions (:mod:`geocoder.mosaic.dense_neighbours`); the summary's ``dense_refined``
        says how each scene was refined. The fields are kept in the store (group
        ``dense/<n>``); scenes connected to no refined scene keep their model. ``"control"``:
        only the control scenes are refined.
    model : {"polynomial", "linescanner", "rpc"}
        Every scene's model in the block adjustment and the output: a polynomial of map
        coordinates of ``order``; the line scanner the scene carries (GeoTIFF tag
        ``GEOCODER_LINESCANNER`` or a ``geocoder simulate`` satellite store), its position
        and yaw adjusted (:data:`geocoder.mosaic.sensors.LINESCANNER_FREE`); or its RPCs
        with an affine bias correction in image space. A scene that carries neither RPCs nor
        a line scanner is placed blind on the reference; with a model that needs what it
        lacks, an :class:`~geocoder.errors.InputError` names it.
    dem : str or PathLike, optional
        DEM (heights in metres, ellipsoidal for the sensor models; reprojected to the
        reference's CRS if it has another): the ground heights of control and tie points,
        bilinear, and of every output pixel, which is mapped into each scene with its height.
        The store then holds ``height (y, x)``. Without it heights are 0.
    report : str or PathLike, optional
        Also write the report directory (:func:`geocoder.mosaic.write_report`: Markdown
        with the overlap graph, the adjustment and the seams, and figures); refused before
        the job if it exists and geocoder did not write it.
    resume : bool
        Continue the unfinished job writing ``out`` (same inputs, options and version):
        pairs, the adjustment and output tiles finished by an earlier, interrupted run are not
        computed again. False starts afresh.
    show_progress : Progress or bool, optional
        Progress receiver, as in :func:`geocoder.register`.
    georeference_sigma : float
        Without ``reference`` and ``control``: the standard deviation (scene pixels) of every
        scene's georeference, which then controls the block as a grid of 5 x 5 points per
        scene observed with it (the block lands where the georeferences say on average).

    Returns
    -------
    xarray.Dataset
        ``mosaic (band, y, x)`` float32, ``source (y, x)`` uint16 (index into
        ``attrs["scenes"]``, 65535 = none), ``status (y, x)`` uint8 (what the pixel's position
        in its source scene rests on, :class:`~geocoder.status.Status` with CF
        ``flag_values``/``flag_meanings``: ``matched`` or ``filled`` from the dense field,
        ``model`` (or ``blunder``, ``no_texture`` where the dense matcher rejected or could
        not match it) from the adjusted model, ``outside`` where no scene covers it),
        ``sigma_x``, ``sigma_y (y, x)`` float32 (standard deviation of that position along
        the output's columns and rows, output pixels: the dense match's where matched, else
        the adjustment's covariance propagated to the pixel plus the scene's mean squared
        residual; a feathered pixel's are its ``source`` scene's;
        :mod:`geocoder.mosaic.layers`), ``height (y, x)`` with a ``dem``, the output's CRS
        and transform (the reference's by default); ``attrs``: the adjusted ``models``
        (``models_crs``: their CRS, when not the output's), the ``radiometry`` (gain, offset
        per scene and band) and the ``summary`` (JSON). With ``out``, overview levels of every
        variable (``status`` and ``source`` nearest, the others averaged).
    """
    if not scenes:
        raise InputError("scenes", "no scenes given")
    if tile is None:
        tile = get_option("tile")
    if not 1 <= order <= 3:
        raise ValueError(f"order must be 1, 2 or 3, got {order}")
    if not 0.0 <= check_points < 1.0:
        raise ValueError(f"check_points must be in [0, 1), got {check_points}")
    if seams not in ("least-cost", "centre"):
        raise ValueError(f"seams must be 'least-cost' or 'centre', got {seams!r}")
    if model not in KINDS:
        raise ValueError(f"model must be one of {', '.join(KINDS)}, got {model!r}")
    if dense not in (False, True, "control"):
        raise ValueError(f"dense must be True, False or 'control', got {dense!r}")
    if resolution is not None and not (math.isfinite(resolution) and resolution > 0):
        raise ValueError(f"resolution must be a positive number, got {resolution!r}")
    if reference is None and dense:
        raise ValueError("dense refinement matches the scenes against a reference orthoimage: give reference")
    if reference is None and control is None and check_points:
        raise ValueError("check points are withheld control points, and without reference or control there are none "
                         "(the georeferences are no accuracy to check against): give control or reference")
    if not (math.isfinite(georeference_sigma) and georeference_sigma > 0):
        raise ValueError(f"georeference_sigma must be a positive number, got {georeference_sigma!r}")
    opts = RegisterOptions(tile=tile, order=order, dense=False)
    if output_tile is None:
        output_tile = tile
    if output_tile < 16 or output_tile % 16:
        raise ValueError(f"output_tile must be a multiple of 16, got {output_tile}")
    opts.validate()
    extra = [control] if control is not None else []  # the CSV is never written over either
    if reference is not None:
        extra.append(reference)
    if out is not None:
        out = check_output(out, inputs=(*scenes, *extra), overwrite=overwrite)
    if cog is not None:  # refused now, not after the job
        check_output(cog, inputs=(*scenes, *extra, *([out] if out is not None else [])), overwrite=overwrite)
    if report is not None:
        from ..reporting import require_matplotlib

        require_matplotlib()
        check_output(report, inputs=(*scenes, *extra, *([out] if out is not None else []), *([cog] if cog else [])),
                     overwrite=overwrite, option="report")
    opened = [open_scene(s, chunks=tile) for s in scenes]
    virtual = reference is None  # the frame from the scenes' georeferences (geocoder.mosaic.georef)
    ref = virtual_reference(opened, tile) if virtual else open_scene(reference, chunks=tile, grid=True)
    crs = output_crs(ref, reference, resolution, crs)
    given = None
    if control is not None:  # read and checked now, before any work
        pixel = math.sqrt(abs((scene_transform(ref) or Affine.identity()).determinant))
        given = read_control(control, list(scenes), [(s.sizes["y"], s.sizes["x"]) for s in opened],
                             default_sigma=DEFAULT_SIGMA_PX * pixel)
    # what every scene carries (its footprint; the model when asked for): refused now, naming the scene
    carried = [scene_sensor(s, model) if model != "polynomial" else _carried(s) for s in scenes]
    if model != "polynomial" and not ref.attrs.get("georeferenced"):
        raise InputError(reference, f"is not georeferenced: the {model} model needs the reference's CRS")
    dem_scene = None
    if dem is not None:
        dem_scene = _open_dem(dem, ref, tile)
    bands = {s.sizes["band"] for s in opened}
    if len(bands) != 1:
        raise InputError(scenes[0], f"the scenes have different band counts {sorted(bands)}; give scenes with the same bands")
    transform = scene_transform(ref) or Affine.identity()
    summary = MosaicSummary(scenes=[s.attrs["source"] for s in opened], seam_mode=seams)
    timer = _Timer(summary)  # type: ignore[arg-type]
    allowed = set(range(len(scenes)) if control_scenes is None else control_scenes)
    # the inputs' content identity and the version, as register's: a scene, reference or DEM
    # replaced at the same path, or another geocoder, must not reuse the job's finished work
    key = fingerprint(scenes=[input_identity(s) for s in scenes],
                      reference=["georeferences", georeference_sigma] if virtual else input_identity(reference),
                      dem=None if dem is None else input_identity(dem), options=repr(opts), output_tile=output_tile,
                      control=sorted(allowed), check_points=check_points, feather=feather, seams=seams, resampling=resampling, balance=balance,
                      dense=dense, model=model, version=__version__,
                      **({} if given is None else {"given": [input_identity(control), given.digest]}),
                      **({} if resolution is None and crs is None else {"grid": [resolution, crs]}))
    job = open_job(out, key, resume) if out is not None else Job(tempfile.mkdtemp(prefix=".geocoder-job-"), key)
    if job.resumed:
        log.info("resuming the job in %s", job.path)
    with JobRun(job, resumable=out is not None) as run, progress.reporting(show_progress), \
            dask_client(client, scheduler) as c:
        run.connected = c.scheduler.address
        progress.current().message(f"Dask dashboard: {c.dashboard_link}")
        with timer("ingest"):
            named = {**({} if virtual else {"reference": ref}), **{f"scene-{k}": s for k, s in enumerate(opened)},
                     **({"dem": dem_scene} if dem_scene is not None else {})}
            ingested = ingest_all(job, named, tile, c)
            ref = ref if virtual else ingested["reference"]
            opened = [ingested[f"scene-{k}"] for k in range(len(opened))]
            heights = None
            if dem_scene is not None:
                dem_scene = ingested["dem"]
                heights = MapDEM(job.file("dem.zarr"), scene_transform(dem_scene), tile)
        ref_reader = None if virtual else WindowReader(job.file("reference.zarr"))
        readers = [WindowReader(job.file(f"scene-{k}.zarr")) for k in range(len(opened))]
        shapes = [(s.sizes["y"], s.sizes["x"]) for s in opened]
        crs_wkt = ref.rio.crs.to_wkt() if ref.attrs.get("georeferenced") else None
        sensors = [None if s is None or crs_wkt is None else sensor_model("rpc" if isinstance(s, RPC) else "linescanner", s, crs_wkt)
                   for s in carried]
        ref_shape = (ref.sizes["y"], ref.sizes["x"])
        priors = [None if m is None else ref_to_scene_prior(m, m.initial_params(), transform, ref_shape, shapes[k], heights)
                  for k, m in enumerate(sensors)]
        threads = _threads(c)
        images, image_readers = [ref, *opened], [ref_reader, *readers]
        with timer("interest points"):
            first = 1 if virtual else 0  # a virtual reference has no image, no points
            points = scene_points(job, ["reference", *(f"scene-{k}" for k in range(len(opened)))][first:],
                                  images[first:], image_readers[first:], opts)
            points = [InterestPoints.concatenate([])] * first + points
        control, ref_to, to_ref, ref_tp = [], {}, {}, {}
        missed: dict[int, GeocoderError] = {}
        if virtual:  # placed by their georeferences; controlled by them unless the CSV controls the block
            for k, scene in enumerate(opened):
                if not scene.attrs.get("georeferenced"):  # placed by its neighbours, below
                    missed[k] = InputError(scene.attrs["source"], "has no georeference")
                    continue
                to_ref[k], ref_to[k] = georeference_mappings(scene, ref, order)
                if given is None and k in allowed:
                    control.append(georeference_control(k, scene, georeference_sigma))
            summary.georeference_sigma_px = None if given is not None else georeference_sigma
        with timer("control points"):
            found = [] if virtual else match_pairs(
                job, "control", [PairSpec(f"ref-{k}", 0, k + 1, priors[k]) for k in range(len(opened))], images,
                image_readers, points, opts)
            for k, result in enumerate(found):
                if isinstance(result, GeocoderError):
                    missed[k] = result
                    continue
                tp, mapping, _ = result
                tp = tp.select(tp.inlier)
                ref_tp[k] = tp
                ref_to[k] = mapping
                to_ref[k] = fit_polymap(tp.dist_x, tp.dist_y, tp.base_x, tp.base_y, order=order)
                if k in allowed:
                    ex, ny = pixel_to_world(transform, tp.base_x, tp.base_y)
                    control.append(Matches(-1, k, np.column_stack([ex, ny]), np.column_stack([tp.dist_x, tp.dist_y]),
                                           np.column_stack([tp.sigma_x, tp.sigma_y])))
        summary.control_points = [sum(len(m) for m in control if m.j == k) for k in range(len(opened))]
        if given is not None:  # the CSV's points: control observations as the reference's matches are
            control.extend(given.matches(len(opened)))
            summary.given_file = given.path
        placement = Placement()
        if missed and ref_to:
            with timer("placement by neighbours"):
                near_priors = [priors[k] if priors[k] is not None or not opts.use_georeference
                               else georeference_prior(ref, opened[k]) for k in range(len(opened))]
                placement = place_by_neighbours(job, images, image_readers, points, opts, shapes, to_ref, ref_to,
                                                near_priors)
        for k in range(len(opened)):
            if k in missed and k not in placement.via:
                summary.left_out[str(k)] = (f"{'placed by no georeference' if virtual else 'not found on the reference'} "
                                            f"({missed[k]}), nor on a placed scene ({placement.why_not(k)})")
        summary.placed = {str(k): ("georeference" if virtual else "reference") if k not in missed else
                          f"via scene {placement.via[k]}" if k in placement.via else "not placed"
                          for k in range(len(opened))}
        ties = []
        with timer("tie points"):
            placed = sorted(ref_to)
            overlaps = {(i, j): overlap_fraction(shapes[i], to_ref[i], ref_to[j], shapes[j])
                        for a, i in enumerate(placed) for j in placed[a + 1:]}
            pairs = [ij for ij, share in overlaps.items() if share >= 0.05]
            # both found on the reference: their placements predict the pair to a pixel, no coarse alignment
            matched = {k for k in ref_tp if k not in missed}
            found = match_pairs(job, "ties", [PairSpec(f"pair-{i}-{j}", i + 1, j + 1,
                                                       affine_between(to_ref[i], ref_to[j], shapes[i]),
                                                       placed=i in matched and j in matched) for i, j in pairs],
                                images, image_readers, points, opts)
            for (i, j), result in zip(pairs, found):
                if isinstance(result, GeocoderError):
                    summary.pairs.append({"i": i, "j": j, "ties": 0, "overlap": round(overlaps[i, j], 3),
                                          "problem": str(result)})
                    continue
                tp, _, _ = result
                tp = tp.select(tp.inlier)
                ties.append(Matches(i, j, np.column_stack([tp.base_x, tp.base_y]), np.column_stack([tp.dist_x, tp.dist_y]),
                                    np.column_stack([tp.sigma_x, tp.sigma_y])))
                summary.pairs.append({"i": i, "j": j, "ties": len(tp), "overlap": round(overlaps[i, j], 3)})
        ok = connected_scenes(len(opened), control, ties, min_points=opts.min_tiepoints)
        ok &= np.array([k in to_ref for k in range(len(opened))], dtype=bool)  # CSV points do not place a scene
        for k in range(len(opened)):
            if not ok[k] and str(k) not in summary.left_out:
                summary.left_out[str(k)] = "tied to no control point (no overlap with a controlled scene)"
        block = [k for k in range(len(opened)) if ok[k]]
        if not block:
            raise InputError(reference or scenes[0], "no scene could be placed on the reference")
        index = {k: n for n, k in enumerate(block)}
        used, checks = withhold(control, check_points)
        with timer("block adjustment"):
            def build():
                return build_problem(
                    [shapes[k] for k in block], [scene_to_map(to_ref[k], transform) for k in block],
                    [replace(m, j=index[m.j]) for m in used if m.j in index],
                    [Matches(index[t.i], index[t.j], t.a, t.b, t.sigma) for t in ties if t.i in index and t.j in index],
                    order=order, height=heights,
                    models=None if model == "polynomial" else [(sensors[k], sensors[k].initial_params()) for k in block],
                )

            problem = build()
            result = job.cached("adjustment", lambda: solve(problem, height=heights))
        summary.sigma0, summary.iterations = float(result.sigma0), int(result.iterations)
        points = point_table(problem, result, abs(transform.a))
        summary.rejected = {"robust": int((~result.obs_active).sum()) - int(result.n_snooped),
                            "snooping": int(result.n_snooped)}
        summary.point_sigma_px = point_sigma(points)
        rays = np.bincount(np.bincount(problem.obs_point))
        summary.rays = {str(k): int(v) for k, v in enumerate(rays) if v and k}
        summary.rms_px = [float(np.sqrt(np.mean(np.sum(result.residuals[(problem.obs_frame == n) & result.obs_active] ** 2, 1))))
                          for n in range(len(block))]
        models = [(problem.frames[n].model, result.params[n]) for n in range(len(block))]
        if check_points:
            summary.check_points, summary.check_rmse_px = check_residuals(checks, models, index, len(opened), heights)
        if given is not None:
            summary.given_points, summary.given_rmse_px = check_residuals(
                [m for m in used if m.ground_sigma is not None], models, index, len(opened), heights)
            summary.given_residuals = given_residuals(given, models, index, checks, heights)
        for n, k in enumerate(block):
            # its footprint from its adjusted model, not the overlap's extrapolation (or its georeference)
            if k in placement.via or virtual:
                to_ref[k], ref_to[k] = footprint_from_model(*models[n], transform, to_ref[k], shapes[k], heights)
        summary.block = list(block)
        nbands = opened[0].sizes["band"]
        gains = np.tile([1.0, 0.0], (len(block), nbands, 1))
        if balance:
            with timer("radiometric balance"):
                gains, summary.seam_step = balance_block(
                    [readers[k] for k in block], ref_reader, transform, tile,
                    [] if virtual else [replace(m, j=index[m.j]) for m in control if m.j in index],
                    [Matches(index[t.i], index[t.j], t.a, t.b, t.sigma) for t in ties if t.i in index and t.j in index],
                    nbands)
        ds, grid, out_transform, out_grid = output_grid(ref, [to_ref[k] for k in block], [shapes[k] for k in block],
                                                         output_tile, opened[0].sizes["band"], heights=heights is not None,
                                                         resolution=resolution, crs=crs)
        summary.shape = (ds.sizes["y"], ds.sizes["x"])
        ds.attrs.update(store_attrs(summary, block, models, gains))
        store = job.file("output.zarr")
        if not job.done("output-created"):
            storage.create_store(ds, store)
            job.save("output-created")
        xr.Dataset({name: ("point", points[:, k]) for k, name in enumerate(POINT_COLUMNS)},
                   attrs={"long_name": "adjusted ground points (geocoder.mosaic.block.point_table)",
                          "units": "x, y: map units of the reference's CRS; sigma_x, sigma_y: reference pixels"}
                   ).to_zarr(store, group="points", mode="w", zarr_format=3, consolidated=False)
        fields: list = [None] * len(block)
        if dense:
            with timer("dense refinement"):
                todo = [n for n, k in enumerate(block) if k in allowed and k in ref_tp]
                done = _concurrently(
                    lambda n: refine_scene(job, key, store, n, ref, ref_reader, readers[block[n]], models[n], ref_tp[block[n]],
                                      to_ref[block[n]], shapes[block[n]], transform, opts, heights),
                    todo, "dense refinement (scenes)", threads)
                for n, f in zip(todo, done):
                    fields[n] = f
                # then the scenes without control (or whose refinement failed), against their refined neighbours
                via = {} if dense == "control" else refine_by_neighbours(
                    job, key, store, ref, transform, [readers[k] for k in block], models, [shapes[k] for k in block],
                    [to_ref[k] for k in block], fields, gains,
                    [Matches(index[t.i], index[t.j], t.a, t.b, t.sigma) for t in ties if t.i in index and t.j in index],
                    opts, lambda fn, items, phase: _concurrently(fn, items, phase, threads), heights)
                summary.dense_refined = [
                    "via " + ", ".join(str(block[k]) for k in via[n]) if n in via else "reference" if fields[n] else "not"
                    for n in range(len(block))]
        if resolution is None and crs is None:  # the reference's grid: output pixel = reference pixel - origin
            origin = tuple(int(round(v)) for v in ~transform * (out_transform.c, out_transform.f))  # output (0, 0) in reference pixels
            to_out = [shifted(to_ref[k], origin) for k in block]
            boxes = np.array([footprint_box(to_ref[k], shapes[k], origin) for k in block])
        else:  # output pixels reach the dense fields through the map and the reference's transform
            origin = transform
            to_out = [through_map(to_ref[k], transform, out_grid) for k in block]
            boxes = np.array([footprint_box(f, shapes[k], (0, 0)) for f, k in zip(to_out, block)])
        summary.footprints = [footprint_outline(f, shapes[k]) for f, k in zip(to_out, block)]
        adjustment_figures(summary, problem, result, models, [shapes[k] for k in block],
                            [scene_to_map(to_ref[k], transform) for k in block], to_out, heights)
        grid_shape = (ds.sizes["y"], ds.sizes["x"])
        plan = None
        block_pairs = [(index[p["i"]], index[p["j"]]) for p in summary.pairs
                       if p["i"] in index and p["j"] in index and p["ties"] > 0]
        if seams == "least-cost":
            with timer("seams"):
                plan = plan_seams(job, store, grid_shape, output_tile, out_grid, models, [readers[k] for k in block],
                                  [shapes[k] for k in block], gains, boxes, block_pairs, dem=heights)
                summary.seam_cells_moved = plan.pop("changed")
        covs, unmodelled = scene_uncertainty(problem, result, len(block))
        with timer("mosaic"):
            tasks = {t.key: dask.delayed(mosaic_tile, pure=True)(
                store, (t.row0, t.row1, t.col0, t.col1), out_grid, models, [readers[k] for k in block],
                [shapes[k] for k in block], feather, resampling, gains, fields, origin, boxes, plan, grid_shape, heights,
                covs, unmodelled)
                for t in grid}
            done = job.run_tiles("mosaic", tasks, phase="mosaic tiles")
        seam_figures(summary, [d["seams"] for d in done.values()], block, problem, result)
        summary.job = job.report()
        import zarr

        zarr.open_group(store, mode="r+").attrs.update({
            **store_attrs(summary, block, models, gains),
            "dense_fields": json.dumps([None if f is None else {"group": f["group"], "row0": f["row0"], "col0": f["col0"],
                                                                "shape": list(f["shape"])} for n, f in enumerate(fields)]),
            **({"reference_origin": json.dumps(list(origin))} if not isinstance(origin, Affine) else
               {"reference_transform": json.dumps(list(origin)[:6])}),
            **({"models_crs": out_grid.ref_crs} if isinstance(out_grid, Reprojected) else {}),
        })
        if cog is not None:
            with timer("cog"):
                to_cog(store, cog, variable="mosaic", client=c, blocksize=output_tile,
                       overwrite=overwrite)
        if out is None:
            result_ds = xr.open_zarr(store, decode_coords="all", consolidated=False).load()
        else:
            write_overviews(store, client=c)
            commit_output(store, out, overwrite=overwrite)
    if out is not None:
        result_ds = xr.open_zarr(out, decode_coords="all", consolidated=False)
    if report is not None:
        from .report import write_report

        write_report(out if out is not None else result_ds, report, overwrite=overwrite)
    return result_ds


def _threads(client) -> int:
    """Pairs matched at once: enough small graphs in flight to keep every worker thread busy."""
    return max(2, min(16, 2 * sum(client.nthreads().values())))


def _concurrently(fn, items: list, phase: str, threads: int) -> list:
    """``fn(item)`` for every item, ``threads`` at a time, results in the order of ``items``.

    Every call submits its own small tile graphs; running several at once from client
    threads keeps the cluster busy where one pair of small scenes has fewer tiles than there
    are workers, and overlaps one pair's client-side work with the others' tasks. The
    progress shows one unit per item (the calls' own phases are not shown).
    """
    def quiet(item):
        with progress.reporting(False):
            return fn(item)

    bar = progress.current()
    bar.phase(phase, len(items))
    pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="geocoder-pairs")
    try:
        futures = [pool.submit(contextvars.copy_context().run, quiet, item) for item in items]
        for _ in as_completed(futures):
            bar.advance()
        results = [f.result() for f in futures]
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown()
    bar.close()
    return results


def _carried(path) -> object | None:
    """The RPC or line scanner a scene carries, if any (its footprint for a polynomial block)."""
    for kind in ("rpc", "linescanner"):
        try:
            return scene_sensor(path, kind)
        except (InputError, OSError, ValueError):
            continue
    return None


def _open_dem(path, ref: xr.DataArray, tile: int) -> xr.DataArray:
    """The DEM as a scene in the reference's CRS (reprojected, bilinear, if it has another)."""
    dem = open_scene(path, chunks=tile, grid=True)
    if not dem.attrs.get("georeferenced"):
        raise InputError(path, "the DEM is not georeferenced")
    if not ref.attrs.get("georeferenced"):
        raise InputError(ref.attrs["source"], "is not georeferenced: a DEM needs the reference's CRS")
    if dem.rio.crs != ref.rio.crs:
        from rasterio.enums import Resampling

        attrs = dict(dem.attrs)
        dem = dem.isel(band=[0]).load().rio.reproject(ref.rio.crs, resampling=Resampling.bilinear).chunk(
            {"band": 1, "y": tile, "x": tile})
        dem.attrs.update(attrs)
    return dem.isel(band=[0])


__all__ = ["mosaic"]
