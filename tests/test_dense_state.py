"""The dense state store's layouts: the compact lattice state holds exactly what the full one does."""

from __future__ import annotations

import numpy as np
import pytest
import zarr

from geocoder.match.grow import NFIELDS, UNVISITED
from geocoder.pipeline.dense import DenseOptions, _read_core, _read_state, _write_core, create_state, lattice_step
from geocoder.tiles import TileGrid


def _random_lattice(shape, k, rng):
    """Full-width fields and codes with values on the lattice columns only (as the growth leaves them)."""
    fields = np.full((NFIELDS, *shape), np.nan, dtype=np.float32)
    code = np.full(shape, UNVISITED, dtype=np.int8)
    cols = np.arange(shape[1]) % k == 0
    fields[:, :, cols] = rng.normal(size=(NFIELDS, shape[0], cols.sum())).astype(np.float32)
    code[:, cols] = rng.integers(-1, 6, size=(shape[0], cols.sum())).astype(np.int8)
    return fields, code


@pytest.mark.parametrize("k", [4, 16])
def test_compact_lattice_state_reads_back_as_the_full_state(tmp_path, k):
    rng = np.random.default_rng(3)
    grid = TileGrid.regular(200, 330, 64)  # last tile row and column shorter, width not a multiple of k
    assert lattice_step(grid, DenseOptions(col_step=k, halo=16)) == k
    shape = (grid.height, grid.width)
    fields, code = _random_lattice(shape, k, rng)
    full, compact = str(tmp_path / "full.zarr"), str(tmp_path / "compact.zarr")
    create_state(full, shape, 64)
    create_state(compact, shape, 64, lattice=k)
    slots = np.zeros((len(grid.rows), len(grid.cols)), dtype=np.int8)
    for t in grid:
        slot = (t.iy + t.ix) % 2  # tiles in both slots
        slots[t.iy, t.ix] = slot
        core = (slice(None), slice(t.row0, t.row1), slice(t.col0, t.col1))
        _write_core(zarr.open_group(full, mode="r+"), t, slot, 1, fields[core], code[core[1:]])
        _write_core(zarr.open_group(compact, mode="r+"), t, slot, k, fields[core][..., ::k], code[core[1:]][:, ::k])
        for what in ("code", "fields"):
            a = _read_core(zarr.open_group(full, mode="r"), t, slot, 1, what)
            b = _read_core(zarr.open_group(compact, mode="r"), t, slot, k, what)
            np.testing.assert_array_equal(a, b)
    # windows across tile edges, at every offset from the lattice
    for r0, r1, c0, c1 in [(0, 200, 0, 330), (10, 150, 3, 200), (63, 65, 61, 131), (100, 101, 257, 329), (0, 5, 1, 3)]:
        f_full, c_full = _read_state(full, slots, grid, r0, r1, c0, c1, fields=(0, 1, 2, 3))
        f_comp, c_comp = _read_state(compact, slots, grid, r0, r1, c0, c1, fields=(0, 1, 2, 3), lattice=k)
        np.testing.assert_array_equal(f_full, f_comp)
        np.testing.assert_array_equal(c_full, c_comp)
        np.testing.assert_array_equal(f_comp, fields[:4, r0:r1, c0:c1])
    # the compact arrays are a k-th of the full width
    assert zarr.open_group(compact, mode="r")["lattice"].shape[-1] == -(-330 // k)


def test_lattice_state_only_where_the_growth_is_on_a_lattice():
    grid = TileGrid.regular(1024, 1024, 512)
    assert lattice_step(grid, DenseOptions()) == DenseOptions().col_step  # the default: every 16th column
    assert lattice_step(grid, DenseOptions(col_step=1, halo=4)) == 1  # full growth
    assert lattice_step(grid, DenseOptions(col_step=4, densify="step")) == 1  # the fill reads the full state
    assert lattice_step(TileGrid.regular(1024, 1000, 500), DenseOptions(col_step=16)) == 1  # tiles off the lattice
