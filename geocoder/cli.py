"""Command line: ``geocoder register | compose | ingest | export | mosaic | report | simulate | adjust | demo | cluster up|down``.

Every command calls the same library functions a notebook would; ``--scheduler`` (default
``DASK_SCHEDULER_ADDRESS``) chooses a running Dask cluster, otherwise a local one is started.
"""

from __future__ import annotations

import functools
import logging
import re
import sys
import time

import click

from .errors import ENVIRONMENT_ERRNOS, EXIT_ENVIRONMENT, EXIT_INPUT, EXIT_INTERRUPTED, GeocoderError

log = logging.getLogger("geocoder")


def _setup_logging(verbose: int, quiet: bool) -> None:
    # the progress display names every stage: log lines only with -v (stages, rounds) and -vv
    level = logging.WARNING if quiet or verbose == 0 else (logging.INFO if verbose == 1 else logging.DEBUG)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(message)s", datefmt="%H:%M:%S")
    import distributed  # noqa: F401  (its import configures its loggers; override them after it)

    # Dask's own error logs repeat, with tracebacks, failures the command reports in one line
    noisy = ("distributed", "bokeh", "tornado", "asyncio", "rasterio", "numba")
    names = [n for n in logging.root.manager.loggerDict if n.split(".")[0] in noisy]
    for name in {*noisy, *names}:
        logging.getLogger(name).setLevel(logging.CRITICAL if verbose < 2 else logging.INFO)


def _fail(message: str, code: int) -> None:
    click.echo(f"geocoder: error: {message}", err=True)
    sys.exit(code)


def _friendly(fn):
    """Turn bad option values raised by the library (ValueError) into one line and exit code 2."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except ValueError as exc:
            _fail(str(exc), EXIT_INPUT)

    return wrapper


#: The group's options that a user may also give after the subcommand (``geocoder demo -q``).
_ANYWHERE = re.compile(r"^(-q|--quiet|--verbose|-v+)$")


def _group_options_first(args: list[str], group: click.Group) -> list[str]:
    """``args`` with ``-q``/``-v`` given after the subcommand moved before it (up to a ``--``)."""
    at = next((i for i, a in enumerate(args) if a in group.commands), None)
    if at is None:
        return args
    end = args.index("--") if "--" in args[at:] else len(args)
    moved = [a for a in args[at + 1 : end] if _ANYWHERE.match(a)]
    if not moved:
        return args
    rest = [a for a in args[at + 1 : end] if not _ANYWHERE.match(a)]
    return [*args[:at], *moved, args[at], *rest, *args[end:]]


#: How long (s) zarr's I/O thread may take to stop at exit (zarr's own exit handler waits 0.2 s).
ZARR_STOP_WAIT_S = 10.0

_zarr_wait_registered = False


def _wait_for_zarr_at_exit(timeout: float = ZARR_STOP_WAIT_S) -> None:
    """At exit, give zarr's I/O thread up to ``timeout`` to stop before zarr's exit handler runs.

    zarr's handler asks its event loop to stop, waits 0.2 s for the thread and closes the loop
    anyway: a thread still busy then (starved on a loaded machine, as right after a Ctrl-C while
    the local cluster shuts down) makes the close raise "Cannot close a running event loop",
    which Python prints as a traceback after the command's one-line message (seen in
    ``tests/test_faults.py``'s Ctrl-C test on a loaded run). Registered when a command ends and
    zarr is loaded, so after zarr's own handler, and exit handlers run in reverse order: this
    one stops the loop first and waits. Both run after Python has joined the program's other
    threads, so none of them can still be waiting on that loop (stopping it when the command
    ends instead hung a run whose scheduler had been killed). Nothing to do without zarr.
    """
    global _zarr_wait_registered
    sync = sys.modules.get("zarr.core.sync")
    if _zarr_wait_registered or sync is None:
        return

    def stop() -> None:
        loop, thread = (getattr(sync, name, [None])[0] for name in ("loop", "iothread"))
        if loop is None or thread is None or not thread.is_alive():
            return
        loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout)

    import atexit

    atexit.register(stop)
    _zarr_wait_registered = True


class _Main(click.Group):
    """The ``geocoder`` group: every failure ends as one line ``geocoder: error: ...`` and an exit code.

    2 for bad input and usage, 3 when the machine or the cluster failed (disk full, scheduler
    lost, output held by another job), 130 when interrupted; a traceback only for a bug.
    """

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        try:
            self._main(args, prog_name, complete_var, **extra)
        finally:
            _wait_for_zarr_at_exit()

    def _main(self, args, prog_name, complete_var, **extra):
        from .interrupts import keep_dropped_interrupts

        args = _group_options_first(list(sys.argv[1:] if args is None else args), self)
        try:
            with keep_dropped_interrupts():
                rv = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except click.exceptions.UsageError as exc:
            hint = f" (see '{exc.ctx.command_path} --help')" if exc.ctx is not None else ""
            _fail(exc.format_message() + hint, EXIT_INPUT)
        except click.ClickException as exc:
            _fail(exc.format_message(), exc.exit_code)
        except click.exceptions.Abort:
            _fail("interrupted; finished work is kept, run the same command again to resume", EXIT_INTERRUPTED)
        except GeocoderError as exc:
            _fail(str(exc), exc.exit_code)
        except OSError as exc:
            if exc.errno not in ENVIRONMENT_ERRNOS:
                raise
            where = f"{exc.filename}: " if exc.filename else ""
            _fail(f"{where}{exc.strerror or exc}; free the resource and run the same command again to resume", EXIT_ENVIRONMENT)
        except Exception as exc:
            from .runtime import is_cluster_failure

            if not is_cluster_failure(exc):
                raise
            _fail(f"the Dask cluster failed ({type(exc).__name__}: {exc}); run the same command again to resume",
                  EXIT_ENVIRONMENT)
        sys.exit(rv if isinstance(rv, int) else 0)


scheduler_option = click.option(
    "--scheduler",
    envvar="DASK_SCHEDULER_ADDRESS",
    default=None,
    help="Dask scheduler address or the cluster.json of 'geocoder cluster up' (default: $DASK_SCHEDULER_ADDRESS, else a local cluster).",
)
tile_option = click.option("--tile", default=None, type=click.IntRange(min=64),
                           help="Tile (chunk) size in pixels (a multiple of 64 where tiles are matched). Default: "
                                "geocoder's option 'tile' (Dask config geocoder.tile, e.g. DASK_GEOCODER__TILE), else 512 "
                                "(register: 1024 when the base's smaller side is 2048 px or more).")
overwrite_option = click.option("--overwrite", is_flag=True,
                                help="Replace an existing output if geocoder wrote it (anything else is never replaced).")


def _band_list(value: str | None) -> tuple[int, ...] | None:
    """``"1,2,3"`` -> (1, 2, 3); a bad list is a usage error naming it."""
    if value is None:
        return None
    try:
        bands = tuple(int(v) for v in value.split(",") if v.strip())
    except ValueError:
        raise click.BadParameter(f"{value!r} is not a comma-separated list of band numbers") from None
    if len(bands) < 2 or min(bands) < 1 or len(set(bands)) != len(bands):
        raise click.BadParameter(f"{value!r}: give two or more distinct 1-based bands")
    return bands


@click.group(cls=_Main, context_settings={"help_option_names": ["-h", "--help"]})
@click.option("-v", "--verbose", count=True, help="Log lines of the stages (-vv: debugging output, Dask's logs too).")
@click.option("-q", "--quiet", is_flag=True, help="Only warnings and errors.")
@click.version_option(package_name="geocoder")
@click.pass_context
def main(ctx: click.Context, verbose: int, quiet: bool) -> None:
    """Tile-parallel sub-pixel registration and geocoding of scanner imagery."""
    _setup_logging(verbose, quiet)
    from .progress import reporting

    # progress bars (named phases, tiles done) on standard error unless --quiet
    ctx.with_resource(reporting(not quiet))


@main.command()
@click.argument("base")
@click.argument("distorted")
@click.option("--out", required=True, help="Output Zarr store: a path or an fsspec URL such as s3://bucket/out.zarr (committed atomically).")
@click.option("--resampling", default="bilinear", show_default=True, type=click.Choice(["nearest", "bilinear", "cubic", "lanczos"]))
@tile_option
@click.option("--band", default=1, show_default=True, type=click.IntRange(min=1), help="1-based band used for matching.")
@click.option("--dist-band", default=None, type=click.IntRange(min=1), help="Band of DISTORTED used for matching (default --band).")
@click.option("--bands", default=None, callback=lambda ctx, param, v: _band_list(v),
              help="Comma-separated 1-based bands the dense matching uses at once, e.g. 1,2,3: one geometry, a gain "
                   "and offset per band (the multispectral Otto-Chau, seed 003 sec. 11). Tie points use --band.")
@click.option("--order", default=2, show_default=True, type=click.IntRange(1, 3), help="Order of the global polynomial.")
@click.option("--dense/--no-dense", default=True, show_default=True, help="Match every pixel, or stop at the polynomial.")
@click.option("--nodata", default=None, type=float, help="Extra nodata value of BASE.")
@click.option("--dist-nodata", default=None, type=float, help="Extra nodata value of DISTORTED.")
@click.option("--restart", is_flag=True, help="Do not resume an interrupted run of the same job; start afresh.")
@click.option("--via", default=None,
              help="Intermediate look MIDDLE: register MIDDLE onto BASE and DISTORTED onto MIDDLE, compose the two "
                   "fields and resample DISTORTED once through the chain (seed 003 sec. 10).")
@overwrite_option
@scheduler_option
@_friendly
def register(base, distorted, out, resampling, tile, band, dist_band, bands, order, dense, nodata, dist_nodata, restart, via,
             overwrite, scheduler):
    """Register DISTORTED onto the grid of BASE and write OUT (Zarr).

    An interrupted run leaves its finished tiles next to OUT; running the same command
    again resumes from them (--restart starts afresh).
    """
    from .pipeline.register import register as run

    t0 = time.perf_counter()
    ds = run(
        base, distorted, out=out, resampling=resampling, tile=tile, scheduler=scheduler,
        band=band, dist_band=dist_band, bands=bands, order=order, dense=dense, nodata=nodata, dist_nodata=dist_nodata,
        resume=not restart, overwrite=overwrite, via=via,
    )
    if via is not None:
        _print_chain(ds)
    _print_summary(ds, time.perf_counter() - t0, out)


def _print_chain(ds) -> None:
    import json

    from .pipeline.register import RegisterSummary

    chain = json.loads(ds.attrs["chain"])
    for leg, what in (("first", f"{chain['via']} onto the base"), ("second", f"the distorted image onto {chain['via']}")):
        click.echo(f"[{leg} leg: {what}]")
        for line in RegisterSummary(**chain[leg]).lines():
            click.echo(f"  {line}")
    click.echo("[composed chain]")


@main.command()
@click.argument("ab")
@click.argument("bc")
@click.option("--out", required=True, help="Output Zarr store of the composed field (committed atomically).")
@tile_option
@overwrite_option
@scheduler_option
@_friendly
def compose(ab, bc, out, tile, overwrite, scheduler):
    """Compose the displacement fields AB (register A B) and BC (register B C) into A onto C, written to OUT.

    The second field is interpolated at the positions the first gives; sigma is propagated
    to first order and the status is the worse of the two (outside where the chain breaks).
    """
    import numpy as np

    from .pipeline.compose import compose as run
    from .status import Status

    t0 = time.perf_counter()
    ds = run(ab, bc, out=out, tile=tile, scheduler=scheduler, overwrite=overwrite)
    counts = np.bincount(ds.status.values.ravel(), minlength=len(Status))
    click.echo("pixels: " + ", ".join(f"{Status(i).name.lower()} {int(n)}" for i, n in enumerate(counts) if n))
    click.echo(f"wrote {out} in {time.perf_counter() - t0:.1f} s")


def _print_summary(ds, seconds: float, out: str | None) -> None:
    import json

    from .pipeline.register import RegisterSummary

    summary = RegisterSummary(**json.loads(ds.attrs["summary"]))
    for line in summary.lines():
        click.echo(line)
    if out:
        click.echo(f"wrote {out} in {seconds:.1f} s")


@main.command()
@click.argument("src")
@click.argument("out")
@tile_option
@click.option("--nodata", default=None, type=float, help="Extra nodata value.")
@overwrite_option
@scheduler_option
@_friendly
def ingest(src, out, tile, nodata, overwrite, scheduler):
    """Write SRC (GeoTIFF/COG, path or URL) to a Zarr v3 store OUT (path or fsspec URL) chunked by tile, CRS kept."""
    from .outputs import check_output
    from .runtime import dask_client
    from .scene import ingest as run
    from .scene import open_scene

    check_output(out, inputs=(src,), overwrite=overwrite, option="OUT")
    open_scene(src, nodata=nodata, grid=True)  # a missing or unreadable input fails before a cluster starts
    with dask_client(scheduler=scheduler) as c:
        scene = run(src, out, tile=tile, nodata=nodata, client=c, overwrite=overwrite)  # None: the option
    click.echo(f"wrote {out}: {scene.sizes['band']} band(s), {scene.sizes['y']} x {scene.sizes['x']} px, tile {scene.data.chunksize[-1]}")


@main.command()
@click.argument("store")
@click.option("--var", "variable", default=None,
              help="Variable to export, e.g. registered, dx, status (default: the store's only image variable).")
@click.option("--cog", "cog", required=True, help="Cloud-Optimized GeoTIFF to write (a local path; written whole or not at all).")
@click.option("--blocksize", default=512, show_default=True, type=click.IntRange(min=16), help="Tile side in pixels (a multiple of 16).")
@click.option("--overviews", default=None, type=click.IntRange(min=0),
              help="Overview levels (default: halve until the smallest fits one tile).")
@click.option("--resampling", default=None, type=click.Choice(["average", "nearest"]),
              help="Overview resampling (default: average for floats, nearest for integers such as status).")
@click.option("--compression", default="deflate", show_default=True, type=click.Choice(["deflate", "none"]))
@click.option("--nodata", default=None, type=float, help="Nodata value written for NaN pixels (default: NaN for floats).")
@overwrite_option
@scheduler_option
@_friendly
def export(store, variable, cog, blocksize, overviews, resampling, compression, nodata, overwrite, scheduler):
    """Write one variable of the Zarr STORE geocoder wrote as a Cloud-Optimized GeoTIFF, tile-parallel on Dask.

    A store without a CRS is exported without georeference, with a warning.
    """
    import warnings

    from .cog import to_cog
    from .errors import GeocoderWarning

    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", GeocoderWarning)
        path = to_cog(store, cog, variable=variable, scheduler=scheduler, blocksize=blocksize, overviews=overviews,
                      resampling=resampling, compression=compression, nodata=nodata, overwrite=overwrite)
    for w in caught:
        if issubclass(w.category, GeocoderWarning):
            click.echo(f"geocoder: warning: {w.message}", err=True)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    import rasterio

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)  # warned about above, in our words
        f = rasterio.open(path)
    with f:
        levels = len(f.overviews(1))
        click.echo(f"wrote {cog}: {f.count} band(s) {f.dtypes[0]}, {f.height} x {f.width} px, tile {blocksize}, "
                   f"{levels} overview(s), {path.stat().st_size / 1e6:.1f} MB in {time.perf_counter() - t0:.1f} s")


@main.command()
@click.argument("scenes", nargs=-1, required=True)
@click.option("--reference", default=None,
              help="Orthoimage: the source of control points, and the mosaic's CRS and pixel unless --crs/--resolution say "
                   "otherwise. Without it every scene must be georeferenced (one CRS): placed by its georeference, tied "
                   "to the others, controlled by --control or else by the georeferences (--georeference-sigma).")
@click.option("--georeference-sigma", default=5.0, show_default=True, type=click.FloatRange(min=0, min_open=True),
              help="Without --reference and --control: the scenes' georeference error (px), their weight as control.")
@click.option("--out", required=True, help="Output Zarr store (committed atomically).")
@click.option("--order", default=2, show_default=True, type=click.IntRange(1, 3), help="Polynomial order of every scene's model.")
@click.option("--control-scenes", default=None,
              help="Comma-separated 0-based scenes whose reference matches are control points (default all; the rest are placed by tie points).")
@click.option("--feather", default=8.0, show_default=True, type=click.FloatRange(min=0), help="Blend width across seams, in output pixels.")
@click.option("--seams", "seam_mode", default="least-cost", show_default=True, type=click.Choice(["least-cost", "centre"]),
              help="Seamlines: nearest each scene's centre, or moved from there onto the cut of least grey-value difference.")
@click.option("--resampling", default="bilinear", show_default=True, type=click.Choice(["nearest", "bilinear", "cubic", "lanczos"]))
@click.option("--balance/--no-balance", default=True, show_default=True,
              help="Radiometric balance: a gain and offset per scene and band from the grey values at control and tie points.")
@click.option("--cog", default=None, help="Also write the mosaic as a Cloud-Optimized GeoTIFF (tile-parallel, with overviews).")
@click.option("--dense/--no-dense", default=False, show_default=True,
              help="Refine every control scene pixel by pixel against the reference (scan-line turbulence), "
                   "then the other scenes against their refined neighbours.")
@click.option("--report", default=None,
              help="Also write a report directory: report.md with the overlap graph, adjustment and seams, plus figures.")
@click.option("--model", "model", default="polynomial", show_default=True,
              type=click.Choice(["polynomial", "linescanner", "rpc"]),
              help="Every scene's model: a polynomial of map coordinates (--order), the line scanner it carries, or its RPCs "
                   "with an affine bias correction.")
@click.option("--dem", default=None, help="DEM (m): ground heights of the points and of every output pixel (default 0).")
@click.option("--check-points", default=0.0, show_default=True, type=click.FloatRange(0.0, 1.0, max_open=True),
              help="Share of the control points withheld from the adjustment as check points (reported).")
@click.option("--control", "control_csv", default=None, type=click.Path(dir_okay=False),
              help="Ground control points measured by hand: CSV with columns scene, col, row, x, y [, sigma, id] "
                   "(scene: 0-based index or file name; col/row: scene pixel, centres at integers; x/y: reference CRS).")
@click.option("--resolution", default=None, type=click.FloatRange(min=0, min_open=True),
              help="Output pixel size in units of the output CRS (default: the reference's pixel grid).")
@click.option("--crs", "out_crs", default=None,
              help="Output CRS, e.g. EPSG:32634 (default the reference's); the pixel defaults to the reference's, measured in it.")
@click.option("--restart", is_flag=True, help="Do not resume an interrupted run of the same job; start afresh.")
@tile_option
@overwrite_option
@scheduler_option
@_friendly
def mosaic(scenes, reference, georeference_sigma, out, order, control_scenes, feather, seam_mode, resampling, balance, cog,
           dense, report, model, dem, check_points, control_csv, resolution, out_crs, restart, tile, overwrite, scheduler):
    """Place SCENES on a reference (or by their georeferences) by one block adjustment (control + tie points) and
    write one seamless mosaic."""
    from .mosaic import MosaicSummary
    from .mosaic import mosaic as run

    control = None
    if control_scenes:
        try:
            control = [int(v) for v in control_scenes.split(",")]
        except ValueError:
            raise click.BadParameter(f"{control_scenes!r} is not a comma-separated list of scene numbers",
                                     param_hint="--control-scenes") from None
        bad = [k for k in control if not 0 <= k < len(scenes)]
        if bad:
            raise click.BadParameter(f"scene(s) {bad} do not exist (0..{len(scenes) - 1})", param_hint="--control-scenes")
    if report is not None:  # refused now, not after the job (the library checks it too)
        from .outputs import check_output
        from .reporting import require_matplotlib

        require_matplotlib()
        check_output(report, inputs=(*scenes, *([reference] if reference else []), out, *([cog] if cog else [])),
                     overwrite=overwrite, option="--report")
    t0 = time.perf_counter()
    ds = run(list(scenes), reference=reference, out=out, order=order, tile=tile, control_scenes=control,
             feather=feather, seams=seam_mode, resampling=resampling, balance=balance, scheduler=scheduler,
             overwrite=overwrite, cog=cog, dense=dense, model=model, dem=dem, report=report, resume=not restart,
             check_points=check_points, control=control_csv, resolution=resolution, crs=out_crs,
             georeference_sigma=georeference_sigma)
    import json

    for line in MosaicSummary(**json.loads(ds.attrs["summary"])).lines():
        click.echo(line)
    click.echo(f"wrote {out}{f' and {cog}' if cog else ''} in {time.perf_counter() - t0:.1f} s")
    if report is not None:
        click.echo(f"wrote the report {report}/report.md")


@main.command("report")
@click.argument("store")
@click.option("--out", required=True, help="Report directory to write: report.html and its PNG figures (written whole or not at all).")
@click.option("--base", default=None, help="Base image (default: the path the store's summary records); needed for the HSI check.")
@click.option("--distorted", default=None,
              help="Distorted image (default: the recorded path); needed for the polynomial-only HSI and the grey-level statistics.")
@click.option("--truth", default=None,
              help="True displacement: a Zarr store with dx/dy on the base grid, or the store of 'geocoder simulate' whose ortho is the base.")
@click.option("--band", default=1, show_default=True, type=click.IntRange(min=1), help="1-based band of the images shown.")
@click.option("--max-size", default=1500, show_default=True, type=click.IntRange(min=64),
              help="Largest side (px) of the maps: the finest overview level at most this large.")
@overwrite_option
@click.option("--scheduler", default=None, envvar="DASK_SCHEDULER_ADDRESS",
              help="Run the reductions on this Dask cluster (default: $DASK_SCHEDULER_ADDRESS, else threads in this process).")
@_friendly
def report_command(store, out, base, distorted, truth, band, max_size, overwrite, scheduler):
    """Write the HTML report of the register output STORE: HSI check, disparity, along-track spectrum, statistics."""
    from .reporting import report as run

    t0 = time.perf_counter()
    kwargs = {"base": base, "distorted": distorted, "truth": truth, "band": band, "max_size": max_size, "overwrite": overwrite}
    if scheduler:
        from .runtime import dask_client

        with dask_client(scheduler=scheduler):
            where = run(store, out, **kwargs)
    else:
        where = run(store, out, **kwargs)
    click.echo(f"wrote {where}/report.html in {time.perf_counter() - t0:.1f} s")


@main.command()
@click.option("--frames", "frames_path", required=True, help="Frames JSON (sensor model and start parameters per frame).")
@click.option("--points", "points_path", required=True, help="Ground points CSV (id,role,X,Y,Z,sigma_X,sigma_Y,sigma_Z).")
@click.option("--observations", "obs_path", required=True, help="Image observations CSV (frame,point,x,y,w_xx,w_xy,w_yy).")
@click.option("--out", required=True, help="Output directory.")
@click.option("--robust", is_flag=True, help="Robust re-weighting (eq 20b, then 22b).")
@click.option("--snooping", is_flag=True, help="Data snooping with redundancy numbers.")
@click.option("--scheduler", default=None, envvar="DASK_SCHEDULER_ADDRESS",
              help="Run the adjustment as one task on this Dask cluster (default: in this process; it is gathered on one node).")
@overwrite_option
@_friendly
def adjust(frames_path, points_path, obs_path, out, robust, snooping, scheduler, overwrite):
    """Block adjustment (rectification with one frame) from plain files."""
    from .adjust.run import adjust_files

    s = adjust_files(frames_path, points_path, obs_path, out, robust=robust, snooping=snooping, scheduler=scheduler,
                     overwrite=overwrite)
    click.echo(f"{s['frames']} frame(s), {s['points']} points, {s['observations']} observations, "
               f"{s['rejected']} rejected; sigma0 {s['sigma0']:.3f}; {s['iterations']} iterations")
    if s["check_rms_total_m"] is not None:
        click.echo(f"check points: {s['check_rms_total_m']:.2f} m RMS")
    click.echo(f"wrote {out}/frames.json, points.csv, residuals.csv, report.md")


@main.command()
@click.option("--size", default=1024, show_default=True, type=click.IntRange(256, 16384), help="Side of the demo scene in pixels.")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0), help="Random seed of the scene and the warp.")
@click.option("--out", default="geocoder-demo", show_default=True,
              help="Directory for the demo's files: new, empty, or an earlier demo's.")
@tile_option
@scheduler_option
@_friendly
def demo(size, seed, out, tile, scheduler):
    """Make a synthetic scene and a warped partner, register them, print the error."""
    from .demo import run_demo

    for line in run_demo(size=size, seed=seed, directory=out, tile=tile, scheduler=scheduler):
        click.echo(line)


@main.command()
@click.argument("kind", type=click.Choice(["airborne", "satellite"]))
@click.option("--ortho", required=True, help="Georeferenced orthoimage (projected CRS) used as the ground texture, or 'synthetic'.")
@click.option("--dem", default=None, help="DEM in the ortho's CRS (default: a fractal surface of --relief metres).")
@click.option("--out", required=True, help="Output Zarr store (written atomically).")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0), help="Seed of the DEM, the attitude/orbit deviations and the noise.")
@click.option("--band", default=None, type=click.IntRange(min=1), help="1-based ortho band to render (default all).")
@click.option("--sensor", default="atm", show_default=True, type=click.Choice(["atm", "caesar", "asas"]), help="Airborne sensor.")
@click.option("--tilt", default=0.0, show_default=True, type=click.FloatRange(-60, 60), help="Along-track tilt in degrees (asas).")
@click.option("--rows", default=None, type=click.IntRange(min=32), help="Scan lines (airborne; default: 80 % of the ortho).")
@click.option("--turbulence", default=0.1, show_default=True, type=click.FloatRange(0, 10), help="Roll/pitch standard deviation in degrees (airborne).")
@click.option("--pixel", default=None, type=click.FloatRange(min=0, min_open=True), help="Pixel size in metres (satellite; default twice the ortho's).")
@click.option("--relief", default=100.0, show_default=True, type=click.FloatRange(min=0), help="Relief of the fractal DEM in metres.")
@click.option("--noise", default=0.02, show_default=True, type=click.FloatRange(0, 1), help="Noise sigma as a fraction of the ortho's dynamic range.")
@click.option("--gain", default=1.0, show_default=True, type=click.FloatRange(min=0, min_open=True), help="Radiometric gain.")
@click.option("--offset", default=0.0, show_default=True, type=click.FloatRange(-1, 1), help="Radiometric offset (fraction of the dynamic range).")
@tile_option
@overwrite_option
@scheduler_option
@_friendly
def simulate(kind, ortho, dem, out, seed, band, sensor, tilt, rows, turbulence, pixel, relief, noise, gain, offset, tile, overwrite, scheduler):
    """Render a synthetic KIND scanner image over ORTHO with the exact ground point of every pixel."""
    from .pipeline.simulate import Radiometry
    from .pipeline.simulate import simulate as run

    ds = run(
        kind, ortho, out=out, dem=dem, seed=seed, band=band, sensor=sensor, rows=rows, tilt_deg=tilt,
        turbulence_deg=turbulence, pixel=pixel, relief=relief, radiometry=Radiometry(noise=noise, gain=gain, offset=offset),
        tile=tile, scheduler=scheduler, overwrite=overwrite,
    )
    click.echo(
        f"wrote {out}: {kind} {ds.attrs['sensor_class']} image {ds.sizes['y']} x {ds.sizes['x']} px, "
        f"{ds.sizes['band']} band(s); truth ground_x/ground_y/ground_z in the ortho's CRS"
    )


@main.group()
def cluster() -> None:
    """Start or stop a Dask cluster (scheduler + worker processes) on this machine."""


dir_option = click.option("--dir", "directory", default=None,
                          help="Directory of cluster.json, logs and certificates (default $GEOCODER_CLUSTER_DIR or ~/.geocoder/cluster).")


@cluster.command("up")
@click.option("--workers", default=2, show_default=True, type=click.IntRange(1), help="Worker processes (one thread each).")
@click.option("--tls", is_flag=True, help="TLS with certificates made for this cluster; clients need them (cluster.json points to them).")
@click.option("--memory-limit", default="auto", show_default=True, help="Memory limit per worker (Dask syntax).")
@click.option("--host", default="127.0.0.1", show_default=True, help="Interface the scheduler listens on.")
@click.option("--port", default=0, show_default=True, type=click.IntRange(0, 65535), help="Scheduler port (0: any free one).")
@dir_option
@_friendly
def cluster_up(workers, tls, memory_limit, host, port, directory):
    """Start a scheduler and WORKERS worker processes with the geocoder preload; print the address."""
    from .cluster import up

    info = up(workers, directory=directory, tls=tls, memory_limit=memory_limit, host=host, port=port)
    for line in info.lines():
        click.echo(line)


@cluster.command("down")
@dir_option
@_friendly
def cluster_down(directory):
    """Stop the cluster started by 'geocoder cluster up'."""
    from .cluster import down

    stopped = down(directory)
    click.echo("no cluster was running" if stopped is None else stopped.line())


if __name__ == "__main__":  # pragma: no cover
    main()
