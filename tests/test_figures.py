"""The ingest's figures of a band in one task per chunk (geocoder.kernels.figures) against dask's
own reductions and xarray's coarsen: chunks not aligned to the overview's squares, nodata, bands."""

from __future__ import annotations

import dask
import dask.array as da
import numpy as np
import pytest
import xarray as xr

from geocoder.pipeline.coarse import overview
from geocoder.pipeline.register import _band_statistics, ingest_figures


@pytest.mark.parametrize(("shape", "tile", "factor"), [((3, 1000, 1300), 256, 6), ((1, 700, 500), 128, 4),
                                                       ((2, 300, 300), 64, 1), ((1, 130, 70), 64, 8)])
def test_one_pass_per_chunk_gives_the_reductions_figures(shape, tile, factor):
    rng = np.random.default_rng(1)
    a = rng.normal(size=shape).astype(np.float32)
    a[:, 30:80, 20:60] = np.nan  # nodata across chunk edges
    a[:, :, -7:] = np.nan
    img = xr.DataArray(da.from_array(a, chunks=(-1, tile, tile)), dims=("band", "y", "x"))
    for b in range(shape[0]):
        n, lo, hi, mean = dask.compute(ingest_figures(img.data, b, factor))[0]
        ref = dask.compute(*_band_statistics(img.data[b : b + 1]), overview(img.isel(band=b), factor).data)
        for got, want in zip((n, lo, hi), ref[:3]):
            assert got.dtype == want.dtype
            np.testing.assert_array_equal(got, want)
        assert mean.shape == ref[3].shape == (shape[1] // factor, shape[2] // factor) and mean.dtype == ref[3].dtype
        # the same means up to float32 rounding of a different order of addition; NaN where a square has none
        np.testing.assert_allclose(mean, ref[3], rtol=0, atol=1e-6)


def test_graph_has_one_task_per_chunk_and_reads_each_chunk_once():
    a = np.ones((1, 512, 512), np.float32)
    img = da.from_array(a, chunks=(-1, 128, 128))
    graph = dict(ingest_figures(img, 0, 4).__dask_graph__())
    # the 16 source chunks, a task per chunk and one to combine them
    assert len(graph) == 16 + 16 + 1
