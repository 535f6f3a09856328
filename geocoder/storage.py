"""Where a job's files live: a local directory or any fsspec URL (``s3://``, ``gs://``, ...).

Locations are plain strings, so that they pickle to workers: a local path (made absolute)
or a URL. Filesystems come from :func:`fsspec.core.url_to_fs`, so credentials and
endpoints come from fsspec's configuration (``FSSPEC_S3_ENDPOINT_URL``, ``AWS_*``, an
fsspec config file), which the client and every worker must share.

Two guarantees hold on every filesystem:

* :func:`write_bytes` is all or nothing: a temporary file renamed on local disks, one PUT
  on object stores.
* :func:`commit_store` makes a finished Zarr store appear at its final location only when
  complete. A local directory is renamed into place. Object stores cannot rename: the store's
  objects are copied on the server, the root ``zarr.json`` last; until that object exists
  there is no Zarr store at the final location (a reader fails), never a partial one.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import threading
import uuid
from collections import OrderedDict
from typing import TYPE_CHECKING

import fsspec

if TYPE_CHECKING:
    import xarray as xr
    import zarr

ROOT_METADATA = "zarr.json"


def compressors() -> tuple:
    """The compressor of the arrays geocoder writes: Blosc's LZ4 on byte-shuffled values.

    Against zarr's default (Zstandard, level 3, no shuffle), on a registered 2048² pair's output
    (``benchmarks/bench_speed.py``'s pair; issue 12's note): a tile written in half the time
    (0.072 against 0.141 s for the seven variables of 1024²) and the store 37 against 51 MB;
    the ``--no-dense`` job 15 % faster end to end, the dense job 3 %.
    """
    from zarr.codecs import BloscCodec

    return (BloscCodec(cname="lz4", clevel=5, shuffle="shuffle"),)


def encoding(ds) -> dict:
    """The ``encoding`` of :meth:`xarray.Dataset.to_zarr` that gives every data variable of
    ``ds`` :func:`compressors`, on top of its own encoding (which the argument replaces: its
    ``grid_mapping`` would be lost)."""
    return {name: {**ds[name].encoding, "compressors": compressors()} for name in ds.data_vars}


def create_store(ds: "xr.Dataset", location: str) -> None:
    """Create the Zarr store of ``ds`` without its values: every array (with :func:`encoding`),
    attribute and coordinate, the lazy data variables' chunks left for their writers.

    ``ds.to_zarr(compute=False)`` would also build the Dask graph that stores each lazy variable,
    merged with the graph that computes it, only to drop it; each is given an empty twin of the
    same shape, dtype and chunks instead.
    """
    import dask.array as da

    twin = ds.copy(deep=False)
    for name, var in ds.data_vars.items():
        if isinstance(var.data, da.Array):
            twin[name] = var.copy(deep=False, data=da.empty(var.shape, dtype=var.dtype, chunks=var.data.chunks))
    twin.to_zarr(location, mode="w", zarr_format=3, consolidated=False, compute=False, encoding=encoding(ds))


def is_url(location: str | os.PathLike) -> bool:
    """Whether ``location`` is a URL of a filesystem other than the local one."""
    s = os.fspath(location)
    return "://" in s and not s.startswith(("file://", "local://"))


def normalize(location: str | os.PathLike) -> str:
    """A local path made absolute (``file://`` stripped), or the URL without a trailing slash."""
    s = os.fspath(location)
    if s.startswith(("file://", "local://")):
        s = s.split("://", 1)[1]
    return s.rstrip("/") if is_url(s) else os.path.abspath(s)


def _fs(location: str) -> tuple[fsspec.AbstractFileSystem, str]:
    return fsspec.core.url_to_fs(location)


# s3fs reads an object's size (a HEAD request) before every whole-object read, to split large
# objects over ``max_concurrency`` connections; a Zarr chunk or metadata object is far smaller
# than its block size (50 MB), so the HEAD would only double the requests.
_STORE_OPTIONS = {"s3": {"max_concurrency": 1}}


def open_group(location: str, mode: str = "r") -> "zarr.Group":
    """A Zarr v3 group that geocoder wrote (a job's working stores, an ingested scene, an output).

    The format is given, so opening reads ``zarr.json`` alone (left open, zarr-python also
    probes ``.zgroup``, ``.zattrs`` and ``.zmetadata``: on an object store a failed GET and a
    listing each); on S3 the chunks are read without a HEAD request first.
    """
    import zarr

    protocol = location.split("://", 1)[0] if is_url(location) else None
    options = {"storage_options": dict(_STORE_OPTIONS[protocol])} if protocol in _STORE_OPTIONS else {}
    return zarr.open_group(location, mode=mode, zarr_format=3, **options)


#: Opened arrays of local stores a process keeps (:func:`open_array`): a few per job's stores.
_OPEN_ARRAYS_MAX = 64
_open_arrays: OrderedDict[tuple, "zarr.Array"] = OrderedDict()
_open_arrays_lock = threading.Lock()


def open_array(location: str, name: str, mode: str = "r") -> "zarr.Array":
    """Array ``name`` of a Zarr v3 group that geocoder wrote, opened once per process.

    A tile task reads or writes a few windows of its job's stores; opening the group and then
    the array read both metadata files through zarr's event loop every time (in a small-tile
    job, a fifth of the workers' time). The array object of a local store is kept while its
    metadata file is the same file, unchanged (device, inode, modification time and size:
    :func:`geocoder.chunkcache.array_identity`), so a store written again at the same place
    is opened anew; it keeps no chunk data, so windows written since are read as they are now.
    Arrays on object stores are opened every time.
    """
    from .chunkcache import array_identity

    identity = array_identity(location, name)
    if identity is None:
        return open_group(location, mode=mode)[name]
    key = (mode, identity)
    with _open_arrays_lock:
        array = _open_arrays.get(key)
        if array is not None:
            _open_arrays.move_to_end(key)
            return array
    array = open_group(location, mode=mode)[name]
    with _open_arrays_lock:
        _open_arrays[key] = array
        while len(_open_arrays) > _OPEN_ARRAYS_MAX:
            _open_arrays.popitem(last=False)
    return array


class Arrays:
    """The arrays of a group that geocoder wrote, by name, through :func:`open_array`."""

    def __init__(self, location: str, mode: str = "r") -> None:
        self.location, self.mode = location, mode

    def __getitem__(self, name: str) -> "zarr.Array":
        return open_array(self.location, name, self.mode)


def join(location: str, *parts: str) -> str:
    """``location`` / ``parts``."""
    if is_url(location):
        return "/".join([location.rstrip("/"), *parts])
    return os.path.join(location, *parts)


def split(location: str) -> tuple[str, str]:
    """Parent location and name."""
    if is_url(location):
        parent, _, name = location.rstrip("/").rpartition("/")
        return parent, name
    p = os.path.abspath(location)
    return os.path.dirname(p), os.path.basename(p)


def sibling(location: str, name: str) -> str:
    """A location named ``name`` next to ``location``."""
    return join(split(location)[0], name)


def temporary_sibling(location: str) -> str:
    """A hidden, unique sibling of ``location`` to write into before :func:`commit_store`."""
    return sibling(location, f".{split(location)[1]}.partial-{uuid.uuid4().hex[:8]}")


def exists(location: str) -> bool:
    """Whether a file or directory (a prefix holding objects) is at ``location``."""
    if not is_url(location):
        return os.path.exists(location)
    fs, path = _fs(location)
    fs.invalidate_cache(path)
    return fs.exists(path)


def is_store(location: str) -> bool:
    """Whether a Zarr v3 store (its root metadata) is at ``location``."""
    return exists(join(location, ROOT_METADATA))


def read_bytes(location: str) -> bytes:
    """The whole file; FileNotFoundError if there is none."""
    if not is_url(location):
        with open(location, "rb") as f:
            return f.read()
    fs, path = _fs(location)
    return fs.cat_file(path)


def write_bytes(location: str, data: bytes) -> None:
    """Write a whole file at once: readers see the old file or the new one, never a part."""
    if is_url(location):
        fs, path = _fs(location)
        fs.pipe_file(path, data)
        return
    folder = os.path.dirname(location)
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", dir=folder)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, location)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def list_names(location: str) -> set[str]:
    """Names of the files directly in ``location`` (empty if there is none)."""
    if not is_url(location):
        try:
            return {e.name for e in os.scandir(location) if e.is_file()}
        except FileNotFoundError:
            return set()
    fs, path = _fs(location)
    fs.invalidate_cache(path)
    try:
        entries = fs.ls(path, detail=True)
    except FileNotFoundError:
        return set()
    return {e["name"].rstrip("/").rsplit("/", 1)[-1] for e in entries if e["type"] == "file"}


def remove(location: str) -> None:
    """Delete a file or directory tree; nothing if it is not there."""
    if not is_url(location):
        if os.path.isdir(location):
            shutil.rmtree(location, ignore_errors=True)
        elif os.path.exists(location):
            os.unlink(location)
        return
    fs, path = _fs(location)
    fs.invalidate_cache(path)
    if fs.exists(path):
        fs.rm(path, recursive=True)
        fs.invalidate_cache(path)


def remove_contents(location: str, *, keep: tuple[str, ...] = ()) -> None:
    """Delete everything directly in the directory ``location`` except the names in ``keep``."""
    if not is_url(location):
        try:
            names = os.listdir(location)
        except FileNotFoundError:
            return
        for name in names:
            if name not in keep:
                remove(os.path.join(location, name))
        return
    fs, path = _fs(location)
    fs.invalidate_cache(path)
    try:
        entries = fs.ls(path, detail=False)
    except FileNotFoundError:
        return
    for entry in entries:
        name = entry.rstrip("/").rsplit("/", 1)[-1]
        if name not in keep:
            remove(join(location, name))


def identity(location: str) -> dict:
    """What tells a changed input from an unchanged one: location, size and time or ETag.

    For a Zarr store (a directory holding ``zarr.json``), its root metadata stands for it.
    """
    location = normalize(location)
    probe = next((join(location, n) for n in (ROOT_METADATA, ".zgroup", ".zarray") if exists(join(location, n))), location)
    if not is_url(location):
        st = os.stat(probe)
        return {"path": location, "size": st.st_size, "mtime_ns": st.st_mtime_ns}
    fs, path = _fs(probe)
    info = fs.info(path)
    stamp = info.get("ETag") or info.get("etag") or info.get("md5Hash") or str(info.get("LastModified") or info.get("mtime") or "")
    return {"path": location, "size": info.get("size"), "stamp": stamp}


def copy_store_body(tmp: str, final: str) -> None:
    """Copy every object of the store ``tmp`` to ``final`` except its root metadata.

    The first step of :func:`commit_store` on object stores; ``final`` is not a Zarr store
    after it (exposed on its own so that this can be tested).
    """
    fs, src = _fs(tmp)
    _, dst = _fs(final)
    fs.invalidate_cache(src)
    files = [f for f in fs.find(src) if f != f"{src}/{ROOT_METADATA}"]
    if files:
        fs.copy(files, [dst + f[len(src):] for f in files])


def commit_store(tmp: str, final: str) -> None:
    """Make the finished store ``tmp`` appear at ``final``, replacing what was there.

    Callers decide whether ``final`` may be replaced (:func:`geocoder.outputs.commit_output`).
    Local: renames a store or a single file (the old store stays whole, under a hidden name, until the new one has
    taken its name). Object
    stores: the old store is unpublished first (its root metadata deleted), then removed;
    the new store's objects are copied on the server, the root metadata last, and ``tmp``
    is removed.
    """
    if not is_url(final):
        if os.path.exists(final):
            old = sibling(final, f".{split(final)[1]}.old-{uuid.uuid4().hex[:8]}")
            os.rename(final, old)
            os.rename(tmp, final)
            remove(old)
        else:
            os.rename(tmp, final)
        return
    remove(join(final, ROOT_METADATA))
    remove(final)
    copy_store_body(tmp, final)
    fs, src = _fs(tmp)
    _, dst = _fs(final)
    fs.copy(f"{src}/{ROOT_METADATA}", f"{dst}/{ROOT_METADATA}")
    remove(tmp)
