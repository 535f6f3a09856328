"""A job's working directory: what is finished, so that a rerun skips it.

A job keeps a manifest (``manifest.json``: the job's fingerprint, the finished stages and
the tile counts of the last run) and the results of every finished tile and stage as
files written whole (:func:`geocoder.storage.write_bytes`), in a local directory or under
any fsspec URL. The tile-parallel stages go
through :meth:`Job.run_tiles`, which skips tiles whose result is on disk and stores each
new result the moment its task finishes; so a job killed at any point loses at most the
tiles that were running. A rerun with a different fingerprint (other inputs, options or
version) starts afresh.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import re
import time
from typing import Any, Callable

import dask.base
import xarray as xr

from .. import progress, storage
from ..errors import EnvironmentFailure, GeocoderError, OutputError, as_environment_failure
from ..outputs import LOCK_FILE, OutputLock
from ..runtime import compute_as_completed, is_cluster_failure

MANIFEST = "manifest.json"


def fingerprint(**parts: Any) -> str:
    """A stable hash of the job's identity (inputs with their size and time, options, version)."""
    text = json.dumps(parts, sort_keys=True, default=repr)
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def input_identity(src: Any) -> Any:
    """What tells a changed input of a job from an unchanged one, for its :func:`fingerprint`.

    Parameters
    ----------
    src : str, PathLike or xarray.DataArray
        A file, store or URL (its location, size and time or ETag: :func:`geocoder.storage.identity`),
        or an image in memory (the dask token of its data).

    Returns
    -------
    object
        A JSON-able value that changes when the input does; the bare location if it cannot be read.
    """
    if isinstance(src, xr.DataArray):
        return dask.base.tokenize(src.data)
    try:
        return storage.identity(os.fspath(src))
    except OSError:
        return os.fspath(src)


def _dump(value: Any) -> bytes:
    return pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)


class Job:
    """The working directory of one job.

    Parameters
    ----------
    path : str
        Directory or fsspec URL (created if needed).
    key : str
        The job's fingerprint; a directory holding another job's files is emptied.
    target : str, optional
        The output the job writes: the job holds the directory's lock
        (:class:`geocoder.outputs.OutputLock`) from here until :meth:`release` or
        :meth:`remove`, so that a second job to the same output is refused.

    Raises
    ------
    geocoder.errors.EnvironmentFailure
        If another live job holds the lock.
    """

    def __init__(self, path: str, key: str, target: str | None = None) -> None:
        self.path = storage.normalize(path)
        self.key = key
        if not storage.is_url(self.path):
            os.makedirs(self.path, exist_ok=True)
        self.lock = OutputLock(self.path, target or self.path)
        self.lock.acquire()
        try:
            self._open()
        except BaseException:
            self.lock.release()
            raise

    def _open(self) -> None:
        manifest = self._read_manifest()
        if manifest is not None and manifest.get("fingerprint") != self.key:
            storage.remove_contents(self.path, keep=(LOCK_FILE,))
            manifest = None
        self.resumed = manifest is not None and bool(manifest.get("stages"))
        self.manifest = manifest or {"fingerprint": self.key, "created": time.time(), "stages": {}}
        self.tiles: dict[str, dict[str, int]] = {}
        self.recomputed = 0
        self._interrupted_found = not self.resumed
        self._write_manifest()

    # -- manifest ---------------------------------------------------------------------------
    def _read_manifest(self) -> dict | None:
        try:
            return json.loads(storage.read_bytes(storage.join(self.path, MANIFEST)))
        except (OSError, ValueError):
            return None

    def _write_manifest(self) -> None:
        self.manifest["tiles"] = self.tiles
        storage.write_bytes(storage.join(self.path, MANIFEST), json.dumps(self.manifest, indent=1).encode())

    def file(self, *parts: str) -> str:
        """A location inside the working directory (local parent directories created)."""
        p = storage.join(self.path, *parts)
        if not storage.is_url(p):
            os.makedirs(os.path.dirname(p), exist_ok=True)
        return p

    # -- whole-stage results ----------------------------------------------------------------
    def done(self, stage: str) -> bool:
        """Whether ``stage`` finished in this or an earlier run."""
        return stage in self.manifest["stages"]

    def save(self, stage: str, value: Any = None, **info: Any) -> None:
        """Store a stage's result and mark it finished."""
        storage.write_bytes(self.file("stages", f"{stage}.pkl"), _dump(value))
        self.manifest["stages"][stage] = {"finished": time.time(), **info}
        self._write_manifest()

    def load(self, stage: str) -> Any:
        """The stored result of a finished stage."""
        return pickle.loads(storage.read_bytes(storage.join(self.path, "stages", f"{stage}.pkl")))

    def cached(self, stage: str, make: Callable[[], Any], *, tiles: int = 0) -> Any:
        """``make()`` once: a rerun loads the stored result. ``tiles`` counts its tile tasks."""
        if self.done(stage):
            self.count(stage, run=0, skipped=tiles)
            return self.load(stage)
        self.note_unfinished(tiles)
        value = make()
        self.count(stage, run=tiles, skipped=0)
        self.save(stage, value)
        return value

    # -- tile results -----------------------------------------------------------------------
    def run_tiles(self, stage: str, tasks: dict[str, Any], phase: str | None = None) -> dict[str, Any]:
        """Compute the ``tasks`` (tile key -> dask delayed) not finished earlier.

        Every result is written to disk as soon as its task finishes. Returns all results
        (earlier and new) by key.
        """
        folder = self.file("tiles", re.sub(r"[^A-Za-z0-9_.-]+", "_", stage).strip("_"))
        finished = storage.list_names(folder)
        results: dict[str, Any] = {}
        todo: dict[str, Any] = {}
        for key, task in tasks.items():
            if f"{key}.pkl" in finished:
                results[key] = pickle.loads(storage.read_bytes(storage.join(folder, f"{key}.pkl")))
            else:
                todo[key] = task
        if todo:
            self.note_unfinished(len(todo))
        self.count(stage, run=len(todo), skipped=len(results))

        def keep(key: str, value: Any) -> None:
            storage.write_bytes(storage.join(folder, f"{key}.pkl"), _dump(value))

        results.update(_compute(todo, phase or stage, total=len(tasks), skipped=len(results), on_result=keep))
        self._write_manifest()
        return {k: results[k] for k in tasks}

    def note_unfinished(self, n: int) -> None:
        """A stage with ``n`` tile tasks was not finished before this run.

        On a rerun, the first such stage is where the earlier run stopped: its tiles that
        run now may have been started before (an upper bound of the work done twice).
        """
        if not self._interrupted_found:
            self._interrupted_found = True
            self.recomputed += n

    def count(self, stage: str, *, run: int, skipped: int) -> None:
        """Count tile tasks of ``stage`` run now and skipped (finished earlier)."""
        c = self.tiles.setdefault(stage, {"run": 0, "skipped": 0})
        c["run"] += run
        c["skipped"] += skipped

    def report(self) -> dict:
        """Tile tasks run and skipped in this run, and the fraction possibly computed twice."""
        run = sum(c["run"] for c in self.tiles.values())
        skipped = sum(c["skipped"] for c in self.tiles.values())
        total = run + skipped
        return {
            "resumed": self.resumed,
            "tile_tasks": total,
            "run": run,
            "skipped": skipped,
            "recomputed": self.recomputed if self.resumed else 0,
            "recomputed_fraction": (self.recomputed / total) if (self.resumed and total) else 0.0,
        }

    def release(self) -> None:
        """Keep the working directory for a rerun, and give up its lock."""
        self.lock.release()

    def remove(self) -> None:
        """Delete the working directory (after the job's output is committed), lock included."""
        storage.remove(self.path)
        self.lock.held = False


class JobRun:
    """What is left of a job's directory when the job ends, by how it ends.

    Done, or failed on its input (a rerun would fail the same way): removed. Interrupted,
    crashed, disk full, scheduler lost, output taken meanwhile: kept, unlocked, for a rerun to
    resume (only if ``resumable``). Failed before reaching a scheduler (``connected`` unset):
    kept only if an earlier run left work in it. Disk full and a lost cluster are raised as
    :class:`~geocoder.errors.EnvironmentFailure` naming the file or the scheduler.

    Set ``connected`` to the scheduler's address once connected.
    """

    def __init__(self, job: Job, *, resumable: bool) -> None:
        self.job = job
        self.resumable = resumable
        self.connected: str | None = None

    def __enter__(self) -> JobRun:
        return self

    def __exit__(self, kind, exc, tb) -> None:
        failure = None
        if exc is None:
            keep = False
        else:
            failure = as_environment_failure(exc, self.job.path)
            if failure is None and self.connected and is_cluster_failure(exc):
                failure = EnvironmentFailure(self.connected, "lost the Dask scheduler or its workers mid-job "
                                             f"({type(exc).__name__}); run the same command again to resume")
            if self.connected is None:
                keep = self.job.resumed
            else:
                keep = isinstance(failure or exc, (EnvironmentFailure, OutputError)) or not isinstance(exc, GeocoderError)
        if keep and self.resumable:
            self.job.release()
        else:
            self.job.remove()
        if failure is not None:
            raise failure from exc


def _compute(tasks: dict[str, Any], phase: str, *, total: int, skipped: int = 0,
             on_result: Callable[[str, Any], None] | None = None) -> dict[str, Any]:
    """Compute ``tasks`` with a progress phase; ``on_result`` sees each result as it arrives."""
    bar = progress.current()
    bar.phase(phase, total, skipped=skipped)
    results = {}
    for key, value in compute_as_completed(tasks):
        if on_result is not None:
            on_result(key, value)
        results[key] = value
        bar.advance()
    bar.close()
    return results


def run_tiles(job: Job | None, stage: str, tasks: dict[str, Any], phase: str | None = None) -> dict[str, Any]:
    """:meth:`Job.run_tiles` when there is a job; otherwise compute with progress, nothing stored."""
    if job is not None:
        return job.run_tiles(stage, tasks, phase)
    results = _compute(tasks, phase or stage, total=len(tasks))
    return {k: results[k] for k in tasks}
