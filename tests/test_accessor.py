"""The .geocoder accessor delegates to the module functions (same results, no copies of them)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import rasterio
import xarray as xr
from pairs import write_synthetic_pair

from geocoder import open_scene, register
from geocoder.accessor import GeocoderArrayAccessor, GeocoderDatasetAccessor
from geocoder.kernels.polynomial import PolyMap
from geocoder.pipeline.register import RegisterSummary

pytestmark = [pytest.mark.cluster]


def test_import_geocoder_registers_the_accessor():
    assert isinstance(xr.DataArray([1]).geocoder, GeocoderArrayAccessor)
    assert isinstance(xr.Dataset().geocoder, GeocoderDatasetAccessor)
    with pytest.raises(ValueError, match="not a geocoder register output"):
        xr.Dataset().geocoder.summary()


def test_import_geocoder_loads_the_pipeline_on_first_use():
    """``import geocoder`` registers the accessors and answers ``--help`` without the pipeline, its
    kernels and their libraries; the public functions load them when first looked up."""
    code = ("import sys, geocoder, xarray as xr; assert isinstance(xr.Dataset().geocoder, geocoder.accessor.GeocoderDatasetAccessor); "
            "heavy = ('geocoder.pipeline.register', 'numba', 'distributed', 'zarr', 'rasterio'); "
            "assert not [m for m in heavy if m in sys.modules], [m for m in heavy if m in sys.modules]; "
            "from geocoder.pipeline.register import register; assert geocoder.register is register; "
            "assert all(hasattr(geocoder, n) for n in geocoder.__all__)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


def test_accessor_register_ingest_and_cog(tmp_path, client):
    work = write_synthetic_pair(tmp_path, 256, seed=4, max_displacement=3)
    base = open_scene(work / "base.tif", chunks=128)
    ds = base.geocoder.register(open_scene(work / "dist.tif", chunks=128), out=tmp_path / "out.zarr", tile=128,
                                client=client, dense=False)
    direct = register(work / "base.tif", work / "dist.tif", tile=128, client=client, dense=False)
    np.testing.assert_array_equal(ds.dx.values, direct.dx.values)
    np.testing.assert_array_equal(ds.status.values, direct.status.values)
    summary = ds.geocoder.summary()
    assert isinstance(summary, RegisterSummary) and summary.tiepoints > 0
    assert sum(summary.status_counts.values()) == 256 * 256
    mapping = ds.geocoder.mapping()
    assert isinstance(mapping, PolyMap) and mapping.order == 2
    cog = ds.geocoder.to_cog(tmp_path / "registered.tif", variable="registered", client=client, blocksize=128)
    with rasterio.open(cog) as f, rasterio.open(work / "base.tif") as b:
        assert f.crs == b.crs and f.transform == b.transform and f.shape == b.shape
        np.testing.assert_array_equal(f.read(1), ds.registered.values[0])
    scene = base.geocoder.ingest(tmp_path / "base.zarr", tile=128, client=client)
    np.testing.assert_array_equal(scene.values, base.values)
    assert scene.rio.crs == base.rio.crs
