"""Render synthetic scanner images from an orthoimage and a DEM, tile-parallel, to Zarr.

Every output tile runs the sensor model's inverse mode (image -> ground, ray intersected
with the DEM) for its pixels, converts the ground points to the ortho's CRS, reads the ortho
window they fall in from Zarr and samples it once. The store holds ``image`` (band, y, x)
and the exact truth ``ground_x, ground_y, ground_z`` (y, x) of every pixel in the ortho's
CRS (heights: the DEM's, ellipsoidal for satellite frames), the DEM used, and the sensor
parameters as JSON.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import tempfile
from dataclasses import dataclass

import dask.array as da
import numpy as np
import xarray as xr
from affine import Affine

from .. import storage
from ..conventions import pixel_grid
from ..errors import InputError
from ..geometry import pixel_to_world, world_to_pixel
from ..multiscales import write_overviews
from ..options import get_option
from ..outputs import check_output, commit_output, product_attrs
from ..runtime import dask_client
from ..scene import WindowReader, ingest, open_scene
from ..simulate.airborne import AirborneScanner, Attitude, asas, atm, caesar
from ..simulate.satellite import LineScanner, ecef_to_geodetic, landsat_mss_like
from ..simulate.terrain import Terrain, fractal_dem
from ..storage import temporary_sibling

AIRBORNE = {"atm": atm, "caesar": caesar, "asas": asas}


@dataclass(frozen=True)
class Radiometry:
    """Radiometric change of the rendered image: ``gain * ortho + offset + noise``.

    ``noise`` and ``offset`` are fractions of the ortho's dynamic range (p1-p99).
    """

    noise: float = 0.02
    gain: float = 1.0
    offset: float = 0.0


class EcefToCrs:
    """ECEF -> (x, y) in ``crs`` and ellipsoidal height; pickleable, transformer built lazily."""

    def __init__(self, crs_wkt: str) -> None:
        self.crs_wkt = crs_wkt
        self._t = None

    def __getstate__(self):
        return {"crs_wkt": self.crs_wkt}

    def __setstate__(self, state):
        self.crs_wkt, self._t = state["crs_wkt"], None

    @property
    def transformer(self):
        if self._t is None:
            from pyproj import Transformer

            self._t = Transformer.from_crs("EPSG:4326", self.crs_wkt, always_xy=True)
        return self._t

    def lonlat(self, lon_deg, lat_deg):
        return self.transformer.transform(lon_deg, lat_deg)

    def __call__(self, X, Y, Z):
        lat, lon, h = ecef_to_geodetic(X, Y, Z)
        x, y = self.lonlat(np.rad2deg(lon), np.rad2deg(lat))
        return np.asarray(x), np.asarray(y), np.asarray(h)


class GeodeticTerrain:
    """``terrain(lat, lon)`` (radians) for satellite models, from a DEM in a projected CRS."""

    def __init__(self, terrain: Terrain, to_crs: EcefToCrs) -> None:
        self.terrain, self.to_crs = terrain, to_crs

    def __call__(self, lat, lon):
        x, y = self.to_crs.lonlat(np.rad2deg(lon), np.rad2deg(lat))
        return self.terrain(np.asarray(x), np.asarray(y))


def _ground_block(block_info=None, *, sensor, terrain, to_crs):
    (r0, r1), (c0, c1) = block_info[None]["array-location"][1:]
    rr, cc = np.mgrid[r0:r1, c0:c1].astype(np.float64)
    X, Y, Z = sensor.image_to_ground(rr, cc, terrain=terrain)
    if to_crs is not None:
        X, Y, Z = to_crs(X, Y, Z)
    return np.stack([X, Y, Z]).astype(np.float64)


def _image_block(ground, block_info=None, *, reader, transform, method, radiometry, dynamic_range, seed):
    (r0, r1), (c0, c1) = block_info[None]["array-location"][1:]
    px, py = world_to_pixel(transform, ground[0], ground[1])
    out = reader.sample(px, py, method=method)
    rad = radiometry
    rng = np.random.default_rng([seed, r0, c0])  # the same tile always gets the same noise
    noisy = rad.gain * out + rad.offset * dynamic_range + rng.normal(0.0, rad.noise * dynamic_range, out.shape)
    return noisy.astype(np.float32)


def _jsonable(obj):
    if dataclasses.is_dataclass(obj):
        return {f.name: _jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    return obj


def airborne_over(ortho: xr.DataArray, terrain: Terrain, *, sensor: str = "atm", seed: int = 0, rows: int | None = None,
                  tilt_deg: float = 0.0, turbulence_deg: float = 0.1, cover: float = 0.8) -> AirborneScanner:
    """An airborne scanner flying north over the middle of ``ortho``.

    The flying height is chosen so the swath covers ``cover`` of the ortho's width (above
    the highest terrain); the image has ``rows`` lines (default: ``cover`` of the ortho's
    height). Roll and pitch turbulence have a standard deviation of ``turbulence_deg``
    (yaw half of it), correlated over ~30 lines, plus a small heading drift.
    """
    if sensor not in AIRBORNE:
        raise ValueError(f"sensor must be one of {sorted(AIRBORNE)}, got {sensor!r}")
    t = ortho.rio.transform()
    h, w = ortho.sizes["y"], ortho.sizes["x"]
    width_m, height_m = abs(t.a) * w, abs(t.e) * h
    cx, cy = pixel_to_world(t, (w - 1) / 2, (h - 1) / 2)
    kw = {"tilt_deg": tilt_deg} if sensor == "asas" else {}
    probe = AIRBORNE[sensor](**kw)
    half = math.tan(probe.fov / 2)
    ground = float(np.nanmax(terrain.heights))
    flying = ground + cover * width_m / (2 * half)
    probe = AIRBORNE[sensor](height=flying, **kw)
    spacing = probe.flight.line_spacing
    nrows = rows or int(cover * height_m / spacing)
    rng_seed = int(seed)
    sig = math.radians(turbulence_deg)
    attitude = Attitude.turbulent(nrows, seed=rng_seed, roll_sigma=sig, pitch_sigma=sig, yaw_sigma=sig / 2,
                                  drift=(0.0, 0.0, sig / 200))
    y0 = float(cy) - nrows * spacing / 2 - flying * math.tan(math.radians(tilt_deg))
    return AIRBORNE[sensor](height=flying, x0=float(cx), y0=y0, rows=nrows, attitude=attitude,
                            line_time=probe.flight.line_time, **kw)


def satellite_over(ortho: xr.DataArray, *, pixel: float | None = None, seed: int = 0, cover: float = 0.8) -> LineScanner:
    """A LANDSAT-like line scanner frame (917 km) centred on ``ortho``, with ``pixel`` metres.

    The swath and the number of lines cover ``cover`` of the ortho; random orbit and
    attitude deviations come from ``seed``.
    """
    t = ortho.rio.transform()
    h, w = ortho.sizes["y"], ortho.sizes["x"]
    pixel = pixel or 2 * abs(t.a)
    cx, cy = pixel_to_world(t, (w - 1) / 2, (h - 1) / 2)
    from pyproj import Transformer

    lon0, lat0 = Transformer.from_crs(ortho.rio.crs.to_wkt(), "EPSG:4326", always_xy=True).transform(cx, cy)
    swath = cover * abs(t.a) * w
    cols = int(swath / pixel)
    rows = int(cover * abs(t.e) * h / pixel)
    return landsat_mss_like(lat0=float(lat0), lon0=float(lon0), rows=rows, cols=cols, swath=swath, line_spacing=pixel, seed=seed)


def simulate(
    kind: str,
    ortho: str | os.PathLike,
    *,
    out: str | os.PathLike,
    dem: str | os.PathLike | None = None,
    seed: int = 0,
    band: int | None = None,
    sensor: str = "atm",
    rows: int | None = None,
    tilt_deg: float = 0.0,
    turbulence_deg: float = 0.1,
    pixel: float | None = None,
    relief: float = 100.0,
    radiometry: Radiometry = Radiometry(),
    resampling: str = "cubic",
    tile: int | None = None,
    client=None,
    scheduler: str | None = None,
    overwrite: bool = False,
) -> xr.Dataset:
    """Render a synthetic ``airborne`` or ``satellite`` scanner image with per-pixel truth.

    Parameters
    ----------
    kind : {"airborne", "satellite"}
        The sensor: an airborne line scanner (whisk-broom, turbulence) or a satellite
        push-broom line scanner.
    ortho : path
        Georeferenced orthoimage (projected CRS, metres) used as the ground texture, or
        ``"synthetic"`` for a procedural 2048 x 2048 scene at 2 m made on the fly.
    out : path
        Zarr store to write (atomically).
    dem : path, optional
        DEM in the ortho's CRS; default a fractal surface of ``relief`` metres (seeded).
    seed : int
        Seeds the DEM, the attitude/orbit deviations and the noise.
    band : int, optional
        1-based band of the ortho to render; default all bands.
    sensor, rows, tilt_deg, turbulence_deg : airborne options (see :func:`airborne_over`).
    pixel : float, optional
        Satellite pixel size in metres (default twice the ortho's).
    relief : float
        Height range (m) of the fractal DEM made when no ``dem`` is given.
    radiometry : Radiometry
        Gain, offset and noise of the rendered image.
    resampling : str
        Interpolator used to sample the ortho.
    tile : int, optional
        Chunk of the rendered image; default :func:`geocoder.get_option` ``("tile")`` (512
        unless set).
    client, scheduler
        Where to run (as :func:`geocoder.register`).
    overwrite : bool
        Replace an existing ``out`` if geocoder wrote it (never anything else).

    Returns
    -------
    xarray.Dataset
        The store, opened lazily.
    """
    if kind not in ("airborne", "satellite"):
        raise ValueError(f"kind must be 'airborne' or 'satellite', got {kind!r}")
    if tile is None:
        tile = get_option("tile")
    out = check_output(out, inputs=(ortho, dem), overwrite=overwrite)
    if not os.path.isdir(os.path.dirname(out)):
        raise InputError(out, "the output's parent directory does not exist")
    work = tempfile.mkdtemp(prefix=".geocoder-work-", dir=os.path.dirname(os.path.abspath(out)))
    try:
        if os.fspath(ortho) == SYNTHETIC:
            ortho = _synthetic_ortho(work, seed)
        return _simulate(kind, ortho, out, work, dem, seed, band, sensor, rows, tilt_deg, turbulence_deg, pixel,
                         relief, radiometry, resampling, tile, client, scheduler, overwrite)
    finally:
        shutil.rmtree(work, ignore_errors=True)


SYNTHETIC = "synthetic"


def _synthetic_ortho(work: str, seed: int) -> str:
    """A procedural 2048 x 2048 ortho at 2 m in UTM 33N (no files needed)."""
    from ..scene import write_geotiff
    from ..simulate.texture import synthetic_ortho

    path = os.path.join(work, "synthetic-ortho.tif")
    write_geotiff(path, synthetic_ortho((2048, 2048), seed=seed), transform=Affine(2.0, 0, 500000.0, 0, -2.0, 5800000.0),
                  crs="EPSG:32633")
    return path


def _simulate(kind, ortho, out, work, dem, seed, band, sensor, rows, tilt_deg, turbulence_deg, pixel, relief,
              radiometry, resampling, tile, client, scheduler, overwrite) -> xr.Dataset:
    scene = open_scene(ortho, chunks=tile, bands=[band] if band else None)
    if not scene.attrs.get("georeferenced") or not scene.rio.crs.is_projected:
        raise InputError(ortho, "the ortho must be georeferenced in a projected CRS (metres)")
    transform = scene.rio.transform()
    if dem is not None:
        dscene = open_scene(dem, chunks=None)
        terrain = Terrain(np.nan_to_num(dscene.values[0].astype(np.float64), nan=0.0), dscene.rio.transform())
    else:
        size = (min(scene.sizes["y"] // 4, 1024) or 1, min(scene.sizes["x"] // 4, 1024) or 1)
        heights = fractal_dem(size, seed=seed, relief=relief)
        t = transform * Affine.scale(scene.sizes["x"] / size[1], scene.sizes["y"] / size[0])
        terrain = Terrain(heights, t)
    if kind == "airborne":
        sensor_model = airborne_over(scene, terrain, sensor=sensor, seed=seed, rows=rows, tilt_deg=tilt_deg,
                                     turbulence_deg=turbulence_deg)
        terrain_fn, to_crs = terrain, None
    else:
        sensor_model = satellite_over(scene, pixel=pixel, seed=seed)
        to_crs = EcefToCrs(scene.rio.crs.to_wkt())
        terrain_fn = GeodeticTerrain(terrain, to_crs)
    tmp = temporary_sibling(out)
    try:
        with dask_client(client, scheduler) as c:
            ingested = ingest(scene, os.path.join(work, "ortho.zarr"), tile=tile, client=c)
            reader = WindowReader(os.path.join(work, "ortho.zarr"))
            lo, hi = np.nanpercentile(ingested.isel(band=0).values[::4, ::4], [1, 99])
            chunks = tuple(tuple(min(tile, n - i) for i in range(0, n, tile)) for n in (sensor_model.rows, sensor_model.cols))
            ground = da.map_blocks(_ground_block, chunks=((3,), *chunks), dtype=np.float64,
                                   sensor=sensor_model, terrain=terrain_fn, to_crs=to_crs)
            image = da.map_blocks(_image_block, ground, chunks=((reader.shape[0],), *chunks), dtype=np.float32,
                                  reader=reader, transform=transform, method=resampling, radiometry=radiometry,
                                  dynamic_range=float(hi - lo), seed=seed)
            ds = xr.Dataset(
                {
                    "image": (("band", "y", "x"), image),
                    "ground_x": (("y", "x"), ground[0], {"long_name": "ground x in the ortho CRS", "units": "m",
                                                        "standard_name": "projection_x_coordinate"}),
                    "ground_y": (("y", "x"), ground[1], {"long_name": "ground y in the ortho CRS", "units": "m",
                                                        "standard_name": "projection_y_coordinate"}),
                    "ground_z": (("y", "x"), ground[2], {"long_name": "ground height", "units": "m"}),
                    "dem": (("dem_y", "dem_x"), terrain.heights, {"transform": list(terrain.transform)[:6]}),
                },
                coords={"band": np.arange(1, reader.shape[0] + 1)},
                attrs={
                    "kind": kind,
                    "sensor": json.dumps(_jsonable(sensor_model)),
                    "sensor_class": type(sensor_model).__name__,
                    "crs": scene.rio.crs.to_wkt(),
                    "seed": int(seed),
                    "ortho": str(ortho),
                    "radiometry": json.dumps(dataclasses.asdict(radiometry)),
                    **product_attrs("simulate"),
                },
            )
            # the image is in scanner geometry (no grid CRS): x/y are the pixel indices; the
            # ortho's CRS of ground_x/ground_y is in the "crs" attribute
            ds["image"].attrs["long_name"] = "simulated scanner image"
            ds = pixel_grid(ds)
            ds.to_zarr(tmp, mode="w", zarr_format=3, consolidated=False, compute=False,
                       encoding=storage.encoding(ds)).compute()
            write_overviews(tmp, client=c)
        commit_output(tmp, out, overwrite=overwrite)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return xr.open_zarr(out, consolidated=False)


def load_sensor(ds: xr.Dataset) -> AirborneScanner | LineScanner:
    """Rebuild the sensor model of a simulated store from its ``sensor`` attribute."""
    from ..simulate.airborne import FlightLine
    from ..simulate.satellite import Orbit

    d = json.loads(ds.attrs["sensor"])
    if ds.attrs["sensor_class"] == "AirborneScanner":
        att = Attitude(**{k: np.asarray(v) for k, v in d.pop("attitude").items()})
        return AirborneScanner(flight=FlightLine(**d.pop("flight")), attitude=att, **d)
    orbit = Orbit(**d.pop("orbit"))
    return LineScanner(orbit=orbit, deviations=np.asarray(d.pop("deviations")), **d)


def load_terrain(ds: xr.Dataset) -> Terrain:
    """The DEM a simulated store was rendered with."""
    return Terrain(np.asarray(ds.dem.values, dtype=np.float64), Affine(*ds.dem.attrs["transform"]))
