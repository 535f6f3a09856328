# ---
# jupyter:
#   jupytext:
#     formats: py:percent,ipynb
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Registering an image pair on a Dask cluster
#
# This notebook registers a *distorted* scanner image onto the pixel grid of a
# georeferenced *base* image with `geocoder.register`, and looks at what comes out:
#
# 1. connect to a Dask cluster (an existing one, or a local one on this machine);
# 2. make a synthetic demo pair whose true displacement is known;
# 3. register it tile by tile; the result is a lazy, Zarr-backed `xarray.Dataset`;
# 4. plot the displacement field, its precision, the per-pixel status and the images
#    before and after, and compare the field with the truth.
#
# It needs no data. Open it in Jupyter with [jupytext](https://jupytext.readthedocs.io)
# (`jupytext --to ipynb examples/register_pair.py`, or open the `.py` directly), or run it
# as a script: `python examples/register_pair.py` saves every figure as a PNG instead of
# showing it. Environment variables:
#
# | variable | meaning | default |
# |---|---|---|
# | `DASK_SCHEDULER_ADDRESS` | scheduler to connect to | start a local cluster |
# | `GEOCODER_EXAMPLE_SIZE` | side of the demo images in pixels | 1024 |
# | `GEOCODER_EXAMPLE_DIR` | working directory for the images, the Zarr store and the PNGs | `./geocoder-example` |

# %%
import json
import os
import sys
from pathlib import Path

import matplotlib

IN_NOTEBOOK = "ipykernel" in sys.modules
if not IN_NOTEBOOK:
    matplotlib.use("Agg")  # headless: figures are written to PNG files only

import matplotlib.pyplot as plt
import numpy as np
import xarray as xr
from affine import Affine
from distributed import Client
from matplotlib.colors import BoundaryNorm, ListedColormap

import geocoder
import geocoder.runtime
import geocoder.status
from geocoder.pipeline.register import RegisterSummary
from geocoder.scene import write_geotiff
from geocoder.simulate.texture import synthetic_ortho
from geocoder.simulate.warp import make_pair

try:
    from IPython.display import display
except ImportError:  # plain Python without IPython
    display = print

SIZE = int(os.environ.get("GEOCODER_EXAMPLE_SIZE", "1024"))
WORKDIR = Path(os.environ.get("GEOCODER_EXAMPLE_DIR", "geocoder-example")).resolve()
WORKDIR.mkdir(parents=True, exist_ok=True)


def show(fig, name):
    """Save a figure into the working directory; show it in a notebook."""
    path = WORKDIR / f"{name}.png"
    fig.savefig(path, dpi=100, bbox_inches="tight")
    print(f"saved {path}")
    if IN_NOTEBOOK:
        plt.show()
    else:
        plt.close(fig)


# %% [markdown]
# ## 1. Connect to a cluster
#
# All tile-parallel work runs on Dask workers. With `DASK_SCHEDULER_ADDRESS` set (e.g.
# `tcp://scheduler:8786`, `tls://scheduler:8786`, or the `cluster.json` that
# `geocoder cluster up` writes, which also names its TLS certificates) the notebook
# connects to that cluster and checks that its workers run this geocoder version;
# otherwise it starts two local worker processes with one thread each.
#
# * **TLS**: nothing changes in the code. Dask reads the certificates from its
#   configuration, e.g. the environment variables `DASK_DISTRIBUTED__COMM__TLS__CA_FILE`,
#   `DASK_DISTRIBUTED__COMM__TLS__CLIENT__CERT` and `DASK_DISTRIBUTED__COMM__TLS__CLIENT__KEY`
#   set before this kernel starts.
# * **Remote workers** read and write the files themselves, so the working directory
#   must be on a filesystem they share with this machine, at the same path.
#
# The dashboard link shows the tasks of every step live.

# %%
address = os.environ.get("DASK_SCHEDULER_ADDRESS")
if address:
    client = geocoder.runtime.connect(address)
else:
    if not IN_NOTEBOOK and os.name == "posix":
        # As a plain script, "spawn"ed worker processes would run this whole file again.
        import dask

        dask.config.set({"distributed.worker.multiprocessing-method": "fork"})
    cluster = geocoder.runtime.local_cluster(2)
    client = Client(cluster)
print(client)
print("dashboard:", client.dashboard_link)

# %% [markdown]
# ## 2. A demo pair with known truth
#
# `synthetic_ortho` renders a textured rural scene; `make_pair` cuts the *base* image
# from it and renders a *distorted* copy through a smooth field of up to 15 px (an affine
# part plus a low-order polynomial, like a scanner's geometry), with new noise, gain and
# offset. The true displacement `pair.dx`, `pair.dy` is kept for the check at the end.
#
# The base is written as a georeferenced GeoTIFF (UTM 33N, 2 m pixels); the distorted
# image is a raw one, without georeference: registration gives it the base's grid.

# %%
margin = 48
source = synthetic_ortho((SIZE + 2 * margin, SIZE + 2 * margin), seed=0)
pair = make_pair(source, shape=(SIZE, SIZE), seed=0, max_displacement=15.0, margin=margin)

base_path = WORKDIR / "base.tif"
distorted_path = WORKDIR / "distorted.tif"
write_geotiff(base_path, pair.base, transform=Affine(2.0, 0.0, 500000.0, 0.0, -2.0, 4000000.0), crs="EPSG:32633")
write_geotiff(distorted_path, pair.distorted)
print(f"base {pair.base.shape}, distorted {pair.distorted.shape}; "
      f"true displacement up to {np.hypot(pair.dx, pair.dy).max():.1f} px")

# %% [markdown]
# ## 3. Register
#
# `geocoder.register` ingests both images, aligns them coarsely, matches tie points tile
# by tile, fits a robust global polynomial, densifies the match to every pixel
# (least-squares matching grown across tile borders) and resamples the distorted image
# once onto the base grid. `tile=256` is the chunk size of all tile-parallel steps.
#
# The result is written atomically to a Zarr store and returned *opened lazily*: the
# variables are Dask arrays backed by the store on disk.
#
# | variable | content |
# |---|---|
# | `registered` | the distorted image resampled onto the base grid (band, y, x) |
# | `dx`, `dy` | displacement in pixels: position in the distorted image minus position in the base |
# | `status` | what each pixel's displacement rests on (codes below) |
# | `sigma_x`, `sigma_y` | standard deviation of `dx`, `dy` from the least-squares match |
# | `correlation` | correlation coefficient of the match |
#
# The tie points are in the store's `tiepoints` group. (rasterio warns that
# `distorted.tif` has no georeference: that is expected for a raw scan.)

# %%
store = WORKDIR / "registered.zarr"
ds = geocoder.register(base_path, distorted_path, out=store, client=client, tile=256)
display(ds)

# %% [markdown]
# The run's summary (tie points, residuals, pixels per status, time per step) is kept in
# the store's attributes:

# %%
summary = json.loads(ds.attrs["summary"])
print("\n".join(RegisterSummary(**summary).lines()))

# %% [markdown]
# Nothing has been read yet: each variable is a chunked Dask array, and pixels are read
# from the store only when they are needed (`.values`, plotting, `.compute()`).
# For a large scene, select or coarsen first, then compute.

# %%
print(ds.dx.data)
print("chunks:", ds.dx.data.chunksize, "| in memory if computed:", f"{ds.nbytes / 2**20:.1f} MiB")

# %% [markdown]
# ## 4. The displacement field
#
# `dx` and `dy` as images, and as arrows on a coarse subsample (every 1/16 of the side).
# Pixels with status 0 (outside the overlap) are masked.

# %%
inside = (ds.status > 0).values
dx = ds.dx.where(inside).values
dy = ds.dy.where(inside).values

fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
for ax, values, title in ((axes[0], dx, "dx [px]"), (axes[1], dy, "dy [px]")):
    im = ax.imshow(values, cmap="RdBu_r")
    ax.set_title(title)
    fig.colorbar(im, ax=ax, shrink=0.8)
step = max(SIZE // 16, 1)
ys, xs = np.mgrid[step // 2 : SIZE : step, step // 2 : SIZE : step]
axes[2].imshow(pair.base[0], cmap="gray")
axes[2].quiver(xs, ys, dx[ys, xs], dy[ys, xs], color="yellow", angles="xy")
axes[2].set_title("displacement (arrows not to scale)")
for ax in axes:
    ax.set_xlabel("x [px]")
axes[0].set_ylabel("y [px]")
show(fig, "displacement")

# %% [markdown]
# ## 5. Precision and status
#
# `sigma_x`, `sigma_y` are the standard deviations of the least-squares match; their
# length `hypot(sigma_x, sigma_y)` shows where the match is firm (textured fields) and
# where it is weak (smooth areas). The `status` map tells what each pixel rests on;
# `geocoder.status.legend()` gives the code table.

# %%
legend = geocoder.status.legend()
print(legend)
sigma = np.hypot(ds.sigma_x, ds.sigma_y).values
status = ds.status.values

fig, axes = plt.subplots(1, 2, figsize=(12, 5))
im = axes[0].imshow(sigma, cmap="magma", vmin=0, vmax=np.nanpercentile(sigma, 99))
axes[0].set_title("hypot(sigma_x, sigma_y) [px]")
fig.colorbar(im, ax=axes[0], shrink=0.8)
codes = sorted(legend.values())
cmap = ListedColormap(["black", "tab:green", "tab:cyan", "tab:red", "tab:gray", "tab:orange", "tab:olive"][: len(codes)])
norm = BoundaryNorm(np.arange(len(codes) + 1) - 0.5, cmap.N)
im = axes[1].imshow(status, cmap=cmap, norm=norm, interpolation="nearest")
cbar = fig.colorbar(im, ax=axes[1], shrink=0.8, ticks=codes)
cbar.ax.set_yticklabels([f"{code} {name}" for name, code in sorted(legend.items(), key=lambda kv: kv[1])])
axes[1].set_title("status")
show(fig, "sigma_status")

# %% [markdown]
# ## 6. Before and after
#
# A checkerboard alternates squares of the base and the other image: edges that jump at
# the square borders show misregistration. Before, the raw distorted image is laid over
# the base as it is; after, the registered image. The difference images tell the same
# (the remaining difference is noise and the gain/offset between the images).

# %%
registered = ds.registered.isel(band=0).values
distorted = pair.distorted[0]  # same shape as the base here, but not on its grid
base = pair.base[0]


def normalize(image):
    lo, hi = np.nanpercentile(image, [1, 99])
    return (image - lo) / (hi - lo)


def checkerboard(a, b, squares=8):
    yy, xx = np.indices(a.shape) * squares // np.array(a.shape)[:, None, None]
    return np.where((yy + xx) % 2 == 0, a, b)


fig, axes = plt.subplots(2, 2, figsize=(11, 11))
for col, (other, label) in enumerate(((distorted, "before (distorted)"), (registered, "after (registered)"))):
    axes[0, col].imshow(checkerboard(normalize(base), normalize(other)), cmap="gray", vmin=0, vmax=1)
    axes[0, col].set_title(f"checkerboard base / {label}")
    axes[1, col].imshow(normalize(other) - normalize(base), cmap="RdBu_r", vmin=-0.5, vmax=0.5)
    axes[1, col].set_title(f"difference {label} - base")
for ax in axes.ravel():
    ax.set_axis_off()
show(fig, "before_after")

# %% [markdown]
# ## 7. Against the truth
#
# The demo knows the true displacement, so the field can be checked directly: the RMSE of
# `dx` and `dy` against `pair.dx`, `pair.dy` over the pixels with a displacement
# (status > 0). The tie points of the global fit are checked the same way.

# %%
valid = status > 0
ex = (ds.dx.values - pair.dx)[valid]
ey = (ds.dy.values - pair.dy)[valid]
rmse_x, rmse_y = np.sqrt(np.mean(ex**2)), np.sqrt(np.mean(ey**2))
print(f"RMSE against truth: dx {rmse_x:.4f} px, dy {rmse_y:.4f} px, "
      f"total {np.hypot(rmse_x, rmse_y):.4f} px over {valid.mean():.1%} of the base")

tiepoints = xr.open_zarr(store, group="tiepoints", consolidated=False)
tx, ty = pair.field.displacement(tiepoints.base_x.values, tiepoints.base_y.values)
terr = np.hypot(tiepoints.dist_x.values - tiepoints.base_x.values - tx, tiepoints.dist_y.values - tiepoints.base_y.values - ty)
print(f"{tiepoints.sizes['point']} tie points against truth: RMS {np.sqrt(np.mean(terr**2)):.4f} px")

# %% [markdown]
# ## Next steps
#
# * Your own data: pass the paths of a georeferenced base (GeoTIFF/COG/Zarr) and a raw
#   scan to `geocoder.register`; `band=`, `order=`, `resampling=` and `dense=` are
#   described in `help(geocoder.register)`. The same job runs from the shell as
#   `geocoder register base.tif scan.tif --out out.zarr`.
# * The output store opens anywhere with `xarray.open_zarr(path, decode_coords="all")`;
#   `registered` carries the base CRS and transform (`ds.rio.crs`), ready for
#   `ds.registered.rio.to_raster("registered.tif")`.
#
# Close the client (and the local cluster, if one was started):

# %%
client.close()
if not address:
    cluster.close()
