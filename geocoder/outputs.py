"""Where a job may write: output paths that never replace or hide a user's data, and a lock per output.

Rules, checked before a job starts and again when it commits:

* an output that exists is refused unless the caller says ``overwrite``; even then only an
  output that geocoder wrote (a Zarr store whose root attributes carry :data:`PRODUCT_ATTR`,
  or a directory holding :data:`MARKER_FILE`) is replaced, never a user's file or folder;
* an output equal to, inside or containing one of the job's inputs, or equal to or containing
  the working directory, is refused;
* one job at a time writes an output: :class:`OutputLock` is a lock file in the job's
  directory naming its holder (host, pid, start); a lock left by a dead process on this host
  is taken over, one held by a live process (or another host) is refused.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import time
from collections.abc import Iterable

from . import storage
from .errors import EnvironmentFailure, OutputError

log = logging.getLogger("geocoder")

#: Root attribute of every Zarr store geocoder writes: the product ("register", "scene", ...).
PRODUCT_ATTR = "geocoder_product"
#: File that marks a plain directory geocoder wrote (adjustment outputs, the demo's folder).
MARKER_FILE = "geocoder.json"
LOCK_FILE = "lock.json"


def product_attrs(product: str) -> dict[str, str]:
    """Root attributes that mark a store as geocoder's ``product``."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        release = version("geocoder")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree
        release = "0.0.0"
    return {PRODUCT_ATTR: product, "geocoder_version": release}


def write_marker(directory: str, product: str) -> None:
    """Mark ``directory`` as an output geocoder wrote (so that ``overwrite`` may replace it)."""
    storage.write_bytes(storage.join(directory, MARKER_FILE), json.dumps(product_attrs(product)).encode())


def product_of(location: str) -> str | None:
    """The product geocoder wrote at ``location``, or None if geocoder did not write it.

    A Zarr store or a directory carries it in its root attributes or :data:`MARKER_FILE`; a
    GeoTIFF (:func:`geocoder.cog.to_cog`) in its GDAL metadata.
    """
    if not storage.is_url(location) and os.path.isfile(location):
        return _tiff_product(location)
    for name, key in ((storage.ROOT_METADATA, "attributes"), (MARKER_FILE, None)):
        try:
            meta = json.loads(storage.read_bytes(storage.join(location, name)))
        except (OSError, ValueError):
            continue
        attrs = meta.get(key, {}) if key else meta
        if isinstance(attrs, dict) and isinstance(attrs.get(PRODUCT_ATTR), str):
            return attrs[PRODUCT_ATTR]
    return None


def _tiff_product(path: str) -> str | None:
    """The product named in a local GeoTIFF's GDAL metadata (None for any other file)."""
    with open(path, "rb") as f:
        if f.read(4) not in (b"II*\0", b"MM\0*", b"II+\0", b"MM\0+"):
            return None
    import warnings

    import rasterio

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            with rasterio.open(path) as src:
                product = src.tags().get(PRODUCT_ATTR)
    except rasterio.errors.RasterioError:
        return None
    return product or None


def _empty_directory(location: str) -> bool:
    """A local directory with nothing in it (a rename may replace it: nothing is lost)."""
    if storage.is_url(location) or not os.path.isdir(location):
        return False
    with os.scandir(location) as entries:
        return next(entries, None) is None


def _inside(child: str, parent: str) -> bool:
    """Whether ``child`` is ``parent`` or lies below it (normalised locations)."""
    sep = "/" if storage.is_url(parent) else os.sep
    return child == parent or child.startswith(parent.rstrip(sep) + sep)


def _real(location: str) -> str:
    return location if storage.is_url(location) else os.path.realpath(location)


def check_output(
    out: str | os.PathLike | None,
    *,
    inputs: Iterable[object] = (),
    overwrite: bool = False,
    option: str = "--out",
) -> str:
    """Check that a job may write ``out``; return it normalised.

    Parameters
    ----------
    out : str or PathLike
        The output location (local path or fsspec URL).
    inputs : iterable
        The job's inputs (paths or URLs; other objects are ignored).
    overwrite : bool
        Replace an existing output, if geocoder wrote it.
    option : str
        How the user named the output, for messages about an empty one.

    Raises
    ------
    OutputError
        If the output would replace or hide anything geocoder did not write.
    """
    if out is None or not os.fspath(out).strip():
        raise OutputError(option, "the output path is empty")
    final = storage.normalize(out)
    real = _real(final)
    if not storage.is_url(final):
        cwd = os.path.realpath(os.getcwd())
        if _inside(cwd, real):
            raise OutputError(final, "is the working directory or contains it; choose a new path for the output")
        if real == os.path.realpath(os.path.expanduser("~")) or real == os.sep:
            raise OutputError(final, "is a home or root directory; choose a new path for the output")
    for item in inputs:
        if not isinstance(item, (str, os.PathLike)) or not os.fspath(item).strip():
            continue
        source = _real(storage.normalize(item))
        if source == real:
            raise OutputError(final, "is also an input of this job; choose a new path for the output")
        if _inside(real, source):
            raise OutputError(final, f"lies inside the input {source}; choose a path outside it")
        if _inside(source, real):
            raise OutputError(final, f"contains the input {source}; choose a path that does not")
    if storage.exists(final) and not _empty_directory(final):
        product = product_of(final)
        if product is None:
            kind = "directory" if storage.is_url(final) or os.path.isdir(final) else "file"
            raise OutputError(final, f"exists and is a {kind} geocoder did not write; it is never replaced, choose a new path")
        if not overwrite:
            raise OutputError(final, f"exists (a geocoder {product} output); pass --overwrite to replace it")
    return final


def claim_directory(directory: str | os.PathLike, *, product: str, option: str = "--out") -> str:
    """A local directory for a command's several files: new, empty, or one the same command made.

    The directory is created and marked (:data:`MARKER_FILE`), so that running the command
    again may write into it; any other existing directory is refused as by :func:`check_output`.
    """
    final = check_output(directory, overwrite=True, option=option)
    existing = product_of(final) if os.path.isdir(final) else None
    if existing is not None and existing != product:
        raise OutputError(final, f"holds a geocoder {existing} output, not a {product}; choose a new path")
    os.makedirs(final, exist_ok=True)
    write_marker(final, product)
    return final


def commit_output(tmp: str, final: str, *, overwrite: bool = False) -> None:
    """Put the finished output ``tmp`` in place at ``final`` (:func:`geocoder.storage.commit_store`).

    Checked again at the last moment: something that appeared at ``final`` while the job ran
    is replaced only if ``overwrite`` and geocoder wrote it; otherwise ``tmp`` is kept (a
    rerun finishes the job).
    """
    if storage.exists(final) and not _empty_directory(final):
        product = product_of(final)
        if not (overwrite and product is not None):
            what = f"a geocoder {product} output" if product else "something geocoder did not write"
            raise OutputError(final, f"appeared while the job ran ({what}) and was left alone; "
                                     "move it away and run the same command again to finish")
    storage.commit_store(tmp, final)


class OutputLock:
    """One job at a time per output: a lock file in the job's directory.

    The file holds the holder's host, pid, process start time and the start of the job. It is
    created whole (written to a temporary name, then hard-linked, which fails if a lock is
    there) on local disks; on object stores it is written if absent (object stores give no
    exclusive create, so two jobs started within the same second may both take it).

    Parameters
    ----------
    directory : str
        The job's directory (local path or URL).
    target : str
        The output the lock protects, for messages.
    """

    def __init__(self, directory: str, target: str) -> None:
        self.path = storage.join(directory, LOCK_FILE)
        self.target = target
        self.held = False

    @staticmethod
    def _me() -> dict:
        import psutil

        return {"host": socket.gethostname(), "pid": os.getpid(), "process_start": psutil.Process().create_time(),
                "since": time.time()}

    def holder(self) -> dict | None:
        """Who holds the lock (None if nobody)."""
        try:
            return json.loads(storage.read_bytes(self.path))
        except FileNotFoundError:
            return None
        except (OSError, ValueError):
            return {}  # being written or damaged

    @staticmethod
    def _alive(holder: dict) -> bool:
        """Whether the holder may still be running (unknown hosts count as alive)."""
        import psutil

        if holder.get("host") != socket.gethostname():
            return True
        try:
            return abs(psutil.Process(int(holder["pid"])).create_time() - float(holder["process_start"])) < 1.0
        except (psutil.Error, KeyError, TypeError, ValueError):
            return False

    def acquire(self) -> None:
        """Take the lock, taking over one left by a dead process on this host.

        Raises
        ------
        EnvironmentFailure
            If another live job holds it.
        """
        me = json.dumps(self._me()).encode()
        for _ in range(3):
            if self._create(me):
                self.held = True
                return
            holder = self.holder()
            if holder is None:
                continue  # released meanwhile
            if holder == {}:
                try:  # a lock file being written, or one a crash left empty
                    age = time.time() - os.stat(self.path).st_mtime if not storage.is_url(self.path) else 0.0
                except OSError:
                    continue
                if age < 10.0:
                    time.sleep(0.5)
                    continue
            elif self._alive(holder):
                since = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(holder.get("since", 0)))
                raise EnvironmentFailure(
                    self.target,
                    f"another geocoder job is writing it (pid {holder.get('pid')} on {holder.get('host')}, since {since}); "
                    f"wait for it to finish, or if that job is dead delete {self.path}",
                )
            log.warning("taking over the lock of a job that died: %s", holder or "empty lock file")
            storage.remove(self.path)
        raise EnvironmentFailure(self.target, f"cannot take the lock {self.path}")

    def _create(self, data: bytes) -> bool:
        if storage.is_url(self.path):
            if storage.exists(self.path):
                return False
            storage.write_bytes(self.path, data)
            return True
        folder = os.path.dirname(self.path)
        os.makedirs(folder, exist_ok=True)
        tmp = os.path.join(folder, f".lock-{os.getpid()}-{time.monotonic_ns()}")
        with open(tmp, "wb") as f:
            f.write(data)
        try:
            os.link(tmp, self.path)
            return True
        except FileExistsError:
            return False
        finally:
            os.unlink(tmp)

    def release(self) -> None:
        """Give the lock back (only if this process holds it)."""
        if self.held:
            holder = self.holder() or {}
            if holder.get("pid") == os.getpid() and holder.get("host") == socket.gethostname():
                storage.remove(self.path)
            self.held = False
