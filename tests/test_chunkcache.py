"""The per-process cache of decoded scene chunks behind WindowReader.read."""

import os
import time

import numpy as np
import zarr

from geocoder import chunkcache
from geocoder.chunkcache import ChunkCache, array_identity
from geocoder.scene import WindowReader


def _store(path, values, chunk=64):
    g = zarr.open_group(path, mode="w", zarr_format=3)
    a = g.create_array("image", shape=values.shape, chunks=(values.shape[0], chunk, chunk), dtype="float32")
    a[:] = values
    return path


def test_windows_through_the_cache_equal_direct_reads(tmp_path):
    rng = np.random.default_rng(3)
    values = rng.normal(size=(2, 200, 170)).astype(np.float32)
    reader = WindowReader(_store(str(tmp_path / "s.zarr"), values))
    chunkcache._CACHE.clear()
    for r0, r1, c0, c1 in [(0, 200, 0, 170), (10, 75, 60, 130), (-5, 30, 150, 190), (63, 65, 63, 65), (190, 230, -20, 5)]:
        got = reader.read(r0, r1, c0, c1)
        want = np.full((2, r1 - r0, c1 - c0), np.nan, np.float32)
        ra, rb, ca, cb = max(r0, 0), min(r1, 200), max(c0, 0), min(c1, 170)
        want[:, ra - r0 : rb - r0, ca - c0 : cb - c0] = values[:, ra:rb, ca:cb]
        np.testing.assert_array_equal(got, want)
    assert chunkcache._CACHE.nbytes > 0
    # a second read of the whole image comes from the cache, identical
    np.testing.assert_array_equal(WindowReader(reader.store).read(0, 200, 0, 170), values)


def test_a_store_written_again_is_never_served_from_the_cache(tmp_path):
    path = str(tmp_path / "s.zarr")
    chunkcache._CACHE.clear()
    first = np.ones((1, 128, 128), np.float32)
    np.testing.assert_array_equal(WindowReader(_store(path, first)).read(0, 128, 0, 128), first)
    before = array_identity(path, "image")
    time.sleep(0.01)  # a new modification time even on coarse clocks
    second = np.full((1, 128, 128), 2.0, np.float32)
    _store(path, second)
    assert array_identity(path, "image") != before
    np.testing.assert_array_equal(WindowReader(path).read(0, 128, 0, 128), second)


def test_the_cache_is_bounded_in_bytes_and_drops_the_least_recently_used():
    cache = ChunkCache(capacity=3 * 400)
    blocks = {k: np.full(100, k, np.float32) for k in range(5)}  # 400 bytes each
    for k in range(3):
        cache.put((k,), blocks[k])
    assert cache.get((0,)) is not None  # 0 is now the most recently used
    cache.put((3,), blocks[3])
    assert cache.get((1,)) is None and cache.get((0,)) is not None
    assert cache.nbytes <= cache.capacity
    cache.put((9,), np.zeros(1000, np.float32))  # larger than the cache: not kept
    assert cache.get((9,)) is None and cache.nbytes <= cache.capacity
    assert not cache.get((0,)).flags.writeable  # a cached chunk cannot be changed through a window


def test_remote_stores_are_not_cached():
    assert array_identity("s3://bucket/scene.zarr", "image") is None
    assert array_identity(os.path.join("no", "such", "store.zarr"), "image") is None
