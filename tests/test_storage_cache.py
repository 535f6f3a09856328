"""storage.open_array: an array of a local store opened once per process, never stale."""

from __future__ import annotations

import numpy as np
import zarr

from geocoder import storage


def _write_store(path, shape, value):
    g = zarr.open_group(path, mode="w", zarr_format=3)
    a = g.create_array("field", shape=shape, chunks=(4, 4), dtype="float32", fill_value=np.nan, compressors=None)
    a[...] = value


def test_an_array_is_opened_once_and_reads_what_was_written_since(tmp_path):
    path = str(tmp_path / "s.zarr")
    _write_store(path, (8, 8), 1.0)
    first = storage.open_array(path, "field", mode="r+")
    assert storage.open_array(path, "field", mode="r+") is first  # the same object: no metadata read again
    assert storage.Arrays(path, mode="r+")["field"] is first
    # another process (here: another handle) writes a window; the kept array reads it as it is now
    zarr.open_group(path, mode="r+", zarr_format=3)["field"][0:4, 0:4] = 7.0
    np.testing.assert_array_equal(first[0:4, 0:4], 7.0)
    # opened read-only, it is another object (a read-only handle never writes)
    assert storage.open_array(path, "field") is not first


def test_a_store_written_again_at_the_same_place_is_opened_anew(tmp_path):
    path = str(tmp_path / "s.zarr")
    _write_store(path, (8, 8), 1.0)
    assert storage.open_array(path, "field").shape == (8, 8)
    _write_store(path, (12, 4), 2.0)  # a new job's store where the old one was
    again = storage.open_array(path, "field")
    assert again.shape == (12, 4)
    np.testing.assert_array_equal(again[...], 2.0)
