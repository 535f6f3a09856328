"""Dask worker preload: ``dask worker SCHEDULER --preload workers/geocoder_preload.py [--geocoder-version V]``.

Sets the worker environment (:data:`geocoder.runtime.WORKER_ENV`: numeric libraries pinned to
one thread, as parallelism comes from Dask tasks, and a bounded GDAL block cache) where the
process was not started with it, loads (or compiles) the interest and resampling kernels once
per worker process so the first tiles are not slowed by compilation, and logs the geocoder
version the worker runs.

``--geocoder-version V`` (a preload argument: it goes after ``--preload`` and after the
positional scheduler address) makes the worker refuse to start unless the installed geocoder
is exactly version ``V``. Workers built from an older image then fail loudly at start instead
of computing tiles with different code than the client.

* ``dask worker`` command line: the option is validated while ``dask worker`` parses its
  arguments, so the command exits with status 2 and an ``Invalid value for
  '--geocoder-version'`` message naming both versions before anything is started.
* ``Worker(preload=[...], preload_argv=[...])`` or the ``distributed.worker.preload-argv``
  config: the check runs in ``dask_setup``, logs the same message and makes the worker's start
  fail, so it never registers with the scheduler.

The scheduler address must be given positionally when preload arguments are used: ``dask
worker`` collects unknown options as its positional arguments, so without an explicit address
``--geocoder-version`` would be taken for the address.
"""

from __future__ import annotations

import logging
import os

import click
import numba

from geocoder._version import __version__
from geocoder.runtime import WORKER_ENV

# Variables read at process start (the BLAS thread pools, glibc's malloc) only take effect
# when the worker is started with them (the image's ENV, the nanny's environment); GDAL reads
# its cache size when it first opens a file, so setting it here is in time.
for var, value in WORKER_ENV.items():
    os.environ.setdefault(var, value)
# numba read its configuration when geocoder was imported above
numba.config.reload_config()

log = logging.getLogger("geocoder.worker")

# Preload.start() in distributed builds the context under this name; the command-line check in
# distributed.preloading.validate_preload_argv builds it without a name.
_RUNTIME_CONTEXT_NAME = "dask_setup"


def installed_version() -> str:
    return __version__


def check_version(expected: str) -> None:
    """Raise RuntimeError unless the installed geocoder is exactly version ``expected``."""
    expected = str(expected).strip()
    installed = installed_version()
    if expected != installed:
        raise RuntimeError(
            f"geocoder version mismatch: expected geocoder {expected} but this worker has geocoder {installed} "
            "installed; rebuild or re-pull the worker image (or reinstall geocoder) so workers and client run "
            "the same version"
        )


def _validate_version_option(ctx: click.Context, param: click.Parameter, value: str | None) -> str | None:
    if value is None or ctx.info_name == _RUNTIME_CONTEXT_NAME:
        return value  # at run time dask_setup checks and closes the worker instead
    try:
        check_version(value)
    except RuntimeError as exc:
        raise click.BadParameter(str(exc), ctx=ctx, param=param) from None
    return value


def warm_kernels() -> None:
    """Run the interest operator and the resampling kernels once on a tiny input (compiles them or
    loads them from numba's cache; the image's build compiled the whole job, see
    :mod:`geocoder.warmup`)."""
    from geocoder.warmup import warm_small_kernels

    warm_small_kernels()


def _refuse_plugin(exc: Exception):
    """A worker plugin whose setup raises ``exc``."""
    from distributed import WorkerPlugin

    class RefuseToStart(WorkerPlugin):
        name = "geocoder-version-check"

        def setup(self, worker) -> None:
            raise exc

    return RefuseToStart()


def _fail_start(worker, exc: Exception) -> None:
    # An exception raised in dask_setup is only logged by distributed's PreloadManager and the
    # worker would start anyway. Plugins passed to a worker are set up after the preloads, with
    # errors raised, so queueing a failing one makes the worker's start fail (it then closes
    # without registering with the scheduler, and a nanny reports the failure).
    pending = getattr(worker, "_pending_plugins", None)
    if isinstance(pending, tuple | list):
        worker._pending_plugins = (*pending, _refuse_plugin(exc))
    else:  # distributed changed its internals: at least do not serve tasks
        worker.loop.add_callback(worker.close, nanny=True, reason="geocoder-version-mismatch")


@click.command()
@click.option(
    "--geocoder-version",
    default=None,
    metavar="VERSION",
    callback=_validate_version_option,
    help="Refuse to start unless the installed geocoder is exactly this version.",
)
async def dask_setup(worker, geocoder_version: str | None = None) -> None:
    if geocoder_version is not None:
        try:
            check_version(geocoder_version)
        except RuntimeError as exc:
            log.error("refusing to start worker %s: %s", getattr(worker, "address", "?"), exc)
            _fail_start(worker, exc)
            return
    warm_kernels()
    log.info("geocoder %s ready on %s", installed_version(), getattr(worker, "address", "?"))
