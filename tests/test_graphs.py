"""Graph construction tier: the Dask graphs of the per-tile stages, built and never computed.

For a known :class:`~geocoder.tiles.TileGrid` (ragged last row and column) every stage's layer
holds exactly one task per tile, keyed by the tile's block index, and its name is a pure
function of the inputs: building it twice, or in another process, gives the same keys, and
other inputs give other keys. No scheduler runs here; the one Zarr store is only opened for
its shape.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import zarr

from geocoder.kernels.polynomial import PolyMap
from geocoder.pipeline.dense import DenseResult, dense_field
from geocoder.pipeline.resample import model_status, polynomial_displacement, resample
from geocoder.quality.postfilter import PostFilterOptions
from geocoder.scene import IMAGE_VAR, WindowReader
from geocoder.tiles import TileGrid

#: 300 x 520 pixels in tiles of 128: rows (128, 128, 44), columns (128, 128, 128, 128, 8).
GRID = TileGrid.regular(300, 520, 128)
TILES = {(t.iy, t.ix) for t in GRID}
MAPPING = PolyMap.from_affine(np.array([[1.01, 0.02, 3.5], [-0.01, 0.99, -2.25]]))


def layer_keys(array, prefix: str) -> dict[str, set[tuple]]:
    """Block indices of every graph layer whose name starts with ``prefix`` (layer name -> indices)."""
    out: dict[str, set[tuple]] = {}
    for key in array.__dask_graph__():
        if isinstance(key, tuple) and key[0].startswith(prefix):
            out.setdefault(key[0], set()).add(tuple(key[1:]))
    return out


def one_task_per_tile(array, prefix: str, *, leading: tuple = ()) -> str:
    """Assert that the layer ``prefix...`` has exactly one task per tile of :data:`GRID`; its name."""
    layers = layer_keys(array, prefix)
    assert len(layers) == 1, f"expected one layer named {prefix}..., got {sorted(layers)}"
    ((name, blocks),) = layers.items()
    assert blocks == {(*leading, iy, ix) for iy, ix in TILES}
    return name


def make_reader(path: Path, bands: int = 3) -> WindowReader:
    g = zarr.open_group(path, mode="w", zarr_format=3)
    g.create_array(IMAGE_VAR, shape=(bands, 200, 240), chunks=(1, 128, 128), dtype="float32", fill_value=np.nan)
    return WindowReader(str(path))


def build(store: Path, mapping: PolyMap = MAPPING, slots: np.ndarray | None = None,
          options: PostFilterOptions = PostFilterOptions()) -> dict:
    """The lazy arrays of the polynomial and dense registration stages on :data:`GRID`."""
    dx, dy = polynomial_displacement(mapping, GRID.chunks)
    registered = resample(make_reader(store / "distorted.zarr"), dx, dy, method="bilinear")
    slots = np.zeros((len(GRID.rows), len(GRID.cols)), np.int8) if slots is None else slots
    result = DenseResult(str(store / "state.zarr"), 1, True, [0], slots, GRID)
    field = dense_field(result, (dx, dy), options)
    return {"dx": dx, "dy": dy, "registered": registered, "status": model_status(registered), **field}


def key_names(store: Path) -> dict[str, list[str]]:
    """Sorted string keys of every graph :func:`build` makes (JSON-able, for another process)."""
    return {k: sorted(map(str, a.__dask_graph__())) for k, a in build(store).items()}


def test_polynomial_displacement_one_task_per_tile():
    dx, dy = polynomial_displacement(MAPPING, GRID.chunks)
    assert dx.chunks == GRID.chunks and dy.chunks == GRID.chunks
    assert one_task_per_tile(dx, "dx-poly-") == dx.name
    assert one_task_per_tile(dy, "dy-poly-") == dy.name
    assert len(dx.__dask_graph__()) == len(GRID) == 15  # nothing but the tiles


def test_polynomial_displacement_names_follow_the_mapping():
    again = polynomial_displacement(PolyMap.from_affine(np.array([[1.01, 0.02, 3.5], [-0.01, 0.99, -2.25]])), GRID.chunks)
    other = polynomial_displacement(PolyMap.from_affine(np.array([[1.01, 0.02, 3.5], [-0.01, 0.99, -2.0]])), GRID.chunks)
    first = polynomial_displacement(MAPPING, GRID.chunks)
    assert [a.name for a in again] == [a.name for a in first]
    assert set(again[0].__dask_graph__()) == set(first[0].__dask_graph__())
    assert {a.name for a in other}.isdisjoint(a.name for a in first)


def test_polynomial_displacement_names_follow_the_centre():
    moved = PolyMap(coef=MAPPING.coef, order=1, centre=(100.0, 50.0), scale=1.0)
    assert polynomial_displacement(moved, GRID.chunks)[0].name != polynomial_displacement(MAPPING, GRID.chunks)[0].name


def test_resample_and_status_one_task_per_tile(tmp_path):
    dx, dy = polynomial_displacement(MAPPING, GRID.chunks)
    reader = make_reader(tmp_path / "distorted.zarr")
    registered = resample(reader, dx, dy, method="bilinear")
    assert registered.shape == (3, GRID.height, GRID.width)
    name = one_task_per_tile(registered, "_resample_block-", leading=(0,))  # all bands in one task
    status = model_status(registered)
    one_task_per_tile(status, "_status_block-")
    # the whole graph: the displacement tiles, one resampling task and one status task per tile
    assert len(status.__dask_graph__()) == 4 * len(GRID)
    again = resample(WindowReader(str(tmp_path / "distorted.zarr")), dx, dy, method="bilinear")
    assert again.name == name
    assert resample(reader, dx, dy, method="cubic").name != name


def test_dense_field_one_task_per_tile(tmp_path):
    built = build(tmp_path)
    for var in ("dx", "dy", "status", "sigma_x", "sigma_y", "correlation"):
        name = one_task_per_tile(built[var], "dense-field-", leading=(0,))  # the 6 fields of a tile in one task
    assert built["dx"].shape == (GRID.height, GRID.width) and built["dx"].chunks == GRID.chunks
    # the slots and the post-filter options are part of the name: another state is another graph
    flipped = np.ones((len(GRID.rows), len(GRID.cols)), np.int8)
    assert one_task_per_tile(build(tmp_path, slots=flipped)["dx"], "dense-field-", leading=(0,)) != name
    strict = PostFilterOptions(k=3.0)
    assert one_task_per_tile(build(tmp_path, options=strict)["dx"], "dense-field-", leading=(0,)) != name


def test_keys_are_the_same_when_built_twice_and_in_another_process(tmp_path):
    here = key_names(tmp_path)
    assert here == key_names(tmp_path)
    code = (
        "import json, sys\n"
        f"sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
        "from pathlib import Path\n"
        "import test_graphs\n"
        f"print(json.dumps(test_graphs.key_names(Path({str(tmp_path)!r}))))\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    there = json.loads(run.stdout.strip().splitlines()[-1])
    assert there == here
    assert sum(len(v) for v in here.values()) > 10 * len(GRID)
