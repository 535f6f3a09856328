"""Blocks of satellite line-scanner scenes over a real ortho and a DEM, with truth (tests, benchmarks).

Every scene is a push-broom frame of :mod:`geocoder.simulate.satellite` pointed off nadir by
a roll, so that the terrain's relief displaces its pixels across track by ``h tan(roll)``:
neighbours looking from different sides see the same hill in different places, which no 2-D
polynomial per scene follows. The image is rendered by the scanner's inverse mode (each
pixel's ray intersected with the DEM, the ortho sampled there once); the truth of a pixel is
that intersection. A scene carries a *navigation* model (the true scanner with its position
and attitude a little off) as a line-scanner tag and as RPCs fitted to it
(:func:`write_scene`), the two things the mosaic's ``linescanner`` and ``rpc`` models start from.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass

import numpy as np
from affine import Affine

from ..geometry import world_to_pixel
from ..kernels.resample import sample
from ..mosaic.sensors import LINESCANNER_TAG, MapGround, scanner_to_dict
from .satellite import LineScanner, landsat_mss_like
from .terrain import Terrain

__all__ = ["SatelliteScene", "line_scanner_block", "navigation", "satellite_scene", "write_scene"]


@dataclass(frozen=True)
class SatelliteScene:
    """One rendered scene: its true scanner, image and truth mapping.

    Attributes
    ----------
    scanner : LineScanner
        The true sensor.
    image : ndarray, shape (rows, cols), float32
    crs_wkt : str
        The ortho's CRS.
    terrain : Terrain
        The DEM the scene was rendered over (map coordinates, heights in metres).
    ortho_transform : Affine
        The ortho's transform (the truth's pixel grid).
    """

    scanner: LineScanner
    image: np.ndarray
    crs_wkt: str
    terrain: Terrain
    ortho_transform: Affine

    def ground(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """True map point ``(m, 3)`` (E, N, h) of scene pixels (the ray meets the DEM there)."""
        conv = _Conv(self.crs_wkt)
        X, Y, Z = self.scanner.image_to_ground(np.ravel(y), np.ravel(x), terrain=conv.geodetic_terrain(self.terrain))
        return conv.to_map(np.column_stack([X, Y, Z]))

    def to_ortho(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Truth: scene pixel -> ortho pixel (the shape of ``x``)."""
        g = self.ground(x, y)
        ox, oy = world_to_pixel(self.ortho_transform, g[:, 0], g[:, 1])
        return np.reshape(ox, np.shape(x)), np.reshape(oy, np.shape(x))


class _Conv:
    """Map <-> ECEF of one CRS (a :class:`MapGround` without a model)."""

    def __init__(self, crs_wkt: str) -> None:
        self.g = MapGround.__new__(MapGround)
        self.g.crs_wkt, self.g._t = crs_wkt, None

    def to_map(self, ecef: np.ndarray) -> np.ndarray:
        return self.g.from_ecef(ecef)

    def to_ecef(self, ground: np.ndarray) -> np.ndarray:
        return self.g.to_ecef(ground)

    def geodetic_terrain(self, terrain: Terrain):
        fwd = self.g._transformers()[1]

        def h(lat, lon):
            e, n = fwd.transform(np.rad2deg(lon), np.rad2deg(lat))
            return terrain(np.asarray(e), np.asarray(n))

        return h


def satellite_scene(ortho: np.ndarray, ortho_transform: Affine, crs_wkt: str, terrain: Terrain, centre: tuple[float, float],
                    *, size: int, pixel: float, roll: float, seed: int, noise: float = 0.01,
                    gain: float = 1.0, offset: float = 0.0) -> SatelliteScene:
    """A ``size x size`` push-broom scene whose centre pixel sees ``centre`` (E, N), rolled by ``roll`` rad.

    Parameters
    ----------
    ortho : ndarray, shape (rows, cols)
        Ground texture.
    ortho_transform : Affine
    crs_wkt : str
        The ortho's projected CRS.
    terrain : Terrain
        Heights (m, ellipsoidal) in the ortho's CRS.
    centre : (float, float)
        Map point the scene's centre pixel sees.
    size : int
    pixel : float
        Ground sample distance at nadir (m).
    roll : float
        Off-nadir roll (rad); relief displaces pixels across track by about ``h tan(roll)``.
    seed : int
        Seeds the small random orbit and attitude deviations and the noise.
    noise, gain, offset
        Radiometry: ``gain * ortho + offset + N(0, noise * std(ortho))``.

    Returns
    -------
    SatelliteScene
    """
    conv = _Conv(crs_wkt)
    to_lonlat = conv.g._transformers()[0]
    lon_c, lat_c = to_lonlat.transform(*centre)
    lon, lat = lon_c, lat_c
    # the nadir point moves across track by the roll: aim the orbit so the centre pixel lands on ``centre``
    h_c = float(terrain(np.array([centre[0]]), np.array([centre[1]]))[0])
    for _ in range(4):
        sc = landsat_mss_like(lat0=float(lat), lon0=float(lon), rows=size, cols=size, swath=size * pixel, line_spacing=pixel,
                              seed=seed, position_sigma=5.0, attitude_sigma=2e-6)
        dev = np.array(sc.deviations)
        dev[3, 0] += roll
        sc = sc.replace(deviations=dev)
        c = (size - 1) / 2.0
        X, Y, Z = sc.image_to_ground(np.array([c]), np.array([c]), height=h_c)
        e, n, _ = conv.to_map(np.column_stack([X, Y, Z]))[0]
        lon_hit, lat_hit = to_lonlat.transform(e, n)
        lon, lat = lon + (lon_c - lon_hit), lat + (lat_c - lat_hit)
    ys, xs = np.mgrid[0:size, 0:size].astype(np.float64)
    X, Y, Z = sc.image_to_ground(ys.ravel(), xs.ravel(), terrain=conv.geodetic_terrain(terrain))
    g = conv.to_map(np.column_stack([X, Y, Z]))
    ox, oy = world_to_pixel(ortho_transform, g[:, 0], g[:, 1])
    img = sample(np.asarray(ortho, dtype=np.float64), ox.reshape(size, size), oy.reshape(size, size), method="cubic")
    rng = np.random.default_rng(seed)
    img = gain * img + offset + rng.normal(0.0, noise * float(np.nanstd(ortho)), img.shape)
    return SatelliteScene(sc, img.astype(np.float32), crs_wkt, terrain, ortho_transform)


def navigation(scanner: LineScanner, *, seed: int, position_m: float = 15.0, attitude_rad: float = 1e-5) -> LineScanner:
    """The scanner as its navigation knows it: position and attitude offsets and rates a little off.

    Parameters
    ----------
    scanner : LineScanner
    seed : int
    position_m : float
        Standard deviation of the along-, cross-track and radial position offsets (m).
    attitude_rad : float
        Standard deviation of the roll, pitch and yaw offsets (rad).

    Returns
    -------
    LineScanner
    """
    rng = np.random.default_rng(seed)
    dev = np.array(scanner.deviations)
    dev[:3, 0] += rng.normal(0.0, position_m, 3)
    dev[3:, 0] += rng.normal(0.0, attitude_rad, 3)
    half = scanner.rows * scanner.orbit.line_time / 2
    dev[:2, 1] += rng.normal(0.0, 0.2 * position_m / half, 2)
    return scanner.replace(deviations=dev)


def write_scene(path: str | os.PathLike, image: np.ndarray, nav: LineScanner, *, heights: tuple[float, float],
                rpc: bool = True, linescanner: bool = True) -> None:
    """A raw (not georeferenced) GeoTIFF of a scene with what it carries: the navigation's line
    scanner (tag :data:`~geocoder.mosaic.sensors.LINESCANNER_TAG`) and RPCs fitted to it over ``heights``.

    Parameters
    ----------
    path : str or PathLike
    image : ndarray, shape (rows, cols)
    nav : LineScanner
        The scene's model as delivered.
    heights : (float, float)
        Height range of the RPC fit (m).
    rpc, linescanner : bool
        Which of the two to write.
    """
    import warnings

    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    from ..adjust.models import fit_rpc

    profile = {"driver": "GTiff", "width": image.shape[1], "height": image.shape[0], "count": 1, "dtype": "float32",
               "tiled": True, "blockxsize": 256, "blockysize": 256, "compress": "deflate"}
    if rpc:
        profile["rpcs"] = fit_rpc(nav, heights=heights).to_rasterio()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(os.fspath(path), "w", **profile) as dst:
            dst.write(np.asarray(image, dtype=np.float32)[None])
            if linescanner:
                dst.update_tags(**{LINESCANNER_TAG: json.dumps(scanner_to_dict(nav))})


def line_scanner_block(work: str | os.PathLike, ortho: np.ndarray, ortho_transform: Affine, crs_wkt: str, *,
                       relief: float, size: int = 256, grid: int = 2, step: float = 0.6, roll: float = 0.35,
                       seed: int = 0) -> tuple[list, list[str], str, str]:
    """A ``grid x grid`` block of rolled line-scanner scenes over ``ortho`` and a fractal DEM, written to ``work``.

    Scene centres are ``step * size`` ortho pixels apart around the ortho's centre; the
    scenes of even columns look from one side (``+roll``), the others from the other, so
    neighbours see the relief displaced in opposite directions.

    Parameters
    ----------
    work : str or PathLike
        Directory for ``ortho.tif``, ``dem.tif`` and ``scene<k>.tif``.
    ortho : ndarray, shape (rows, cols)
    ortho_transform : Affine
    crs_wkt : str
    relief : float
        Height range of the DEM (m); 0 for flat ground (a DEM of zeros).
    size, grid, step, roll, seed
        Scene size (px), scenes per side, centre spacing (fraction of ``size``), roll (rad), seed.

    Returns
    -------
    scenes : list of SatelliteScene
    paths : list of str
        The scene files (raw GeoTIFFs carrying their navigation's line scanner and RPCs).
    ortho_path, dem_path : str
    """
    from ..scene import write_geotiff
    from .terrain import fractal_dem

    work = os.fspath(work)
    h, w = ortho.shape
    dem_t = ortho_transform * Affine.scale(4, 4)
    heights = fractal_dem((h // 4, w // 4), seed=seed + 100, relief=relief) if relief > 0 else np.zeros((h // 4, w // 4))
    terrain = Terrain(heights, dem_t)
    ortho_path, dem_path = os.path.join(work, "ortho.tif"), os.path.join(work, "dem.tif")
    write_geotiff(ortho_path, ortho.astype(np.float32), transform=ortho_transform, crs=crs_wkt)
    write_geotiff(dem_path, heights.astype(np.float32), transform=dem_t, crs=crs_wkt)
    pixel = abs(ortho_transform.a)
    scenes, paths = [], []
    offsets = (np.arange(grid) - (grid - 1) / 2) * step * size
    for r, dy in enumerate(offsets):
        for c, dx in enumerate(offsets):
            k = r * grid + c
            centre = ortho_transform * ((w - 1) / 2 + dx + 0.5, (h - 1) / 2 + dy + 0.5)
            sc = satellite_scene(ortho, ortho_transform, crs_wkt, terrain, centre, size=size, pixel=pixel,
                                 roll=roll if c % 2 == 0 else -roll, seed=seed + k, gain=1.0 + 0.08 * k, offset=20.0 * k)
            scenes.append(sc)
            paths.append(os.path.join(work, f"scene{k}.tif"))
            write_scene(paths[-1], sc.image, navigation(sc.scanner, seed=seed + 50 + k),
                        heights=(float(heights.min()) - 50.0, float(heights.max()) + 50.0))
    return scenes, paths, ortho_path, dem_path
