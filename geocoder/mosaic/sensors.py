"""Per-scene sensor models of a mosaic: polynomial, line scanner or RPC, all on map ground.

The mosaic's ground points are map coordinates ``(E, N, h)`` in the reference's CRS (metres)
with ``h`` the DEM's height (0 without one). :class:`MapPolynomial` works on them directly;
the rigorous models of :mod:`geocoder.adjust.models` work on ECEF, so :class:`MapGround`
converts (map -> longitude/latitude -> ECEF, heights taken as ellipsoidal) and chains the
ground Jacobian. What a scene carries is read by :func:`scene_sensor`: a GeoTIFF's RPC
metadata, or a line scanner (JSON in the GeoTIFF tag :data:`LINESCANNER_TAG`, or the
``sensor`` attribute of a ``geocoder simulate`` store). Models are stored in a mosaic's
attributes as JSON (:func:`model_to_dict`, :func:`model_from_dict`).
"""

from __future__ import annotations

import json
import os
from typing import Any

import numpy as np

from ..adjust.linescanner_geometry import LineScanner
from ..adjust.models import RPC, LineScannerModel, MapPolynomial, RPCModel
from ..adjust.orbit import Orbit
from ..errors import InputError
from ..geodesy import ecef_to_geodetic, geodetic_to_ecef

__all__ = ["KINDS", "LINESCANNER_FREE", "LINESCANNER_TAG", "MapGround", "model_from_dict", "model_to_dict",
           "scanner_from_dict", "scanner_to_dict", "scene_sensor"]

#: The model kinds of a mosaic.
KINDS = ("polynomial", "linescanner", "rpc")

#: GeoTIFF tag holding a scene's line scanner (JSON of :func:`scanner_to_dict`).
LINESCANNER_TAG = "GEOCODER_LINESCANNER"

#: Line-scanner parameters adjusted in a mosaic: offset and rate of the along- and cross-track
#: position and the yaw offset (indices into the 32 of :meth:`LineScanner.parameters`). Over a
#: scene of a few kilometres the orbit elements, roll and pitch are all but the same unknowns
#: as these (and the radial offset hardly moves a pixel), so five parameters correct the
#: navigation like an affine would, while the terrain's relief displacement comes from the
#: rigorous geometry.
LINESCANNER_FREE = (8, 9, 12, 13, 28)


def scanner_to_dict(s: LineScanner) -> dict:
    """A :class:`LineScanner` as JSON-serialisable values.

    Parameters
    ----------
    s : LineScanner

    Returns
    -------
    dict
        ``orbit`` (its fields), ``rows``, ``cols``, ``ifov``, ``kind``, ``col_time``, ``deviations``.
    """
    from dataclasses import asdict

    return {"orbit": {k: float(v) for k, v in asdict(s.orbit).items()}, "rows": int(s.rows), "cols": int(s.cols),
            "ifov": float(s.ifov), "kind": s.kind, "col_time": float(s.col_time),
            "deviations": np.asarray(s.deviations).tolist()}


def scanner_from_dict(d: dict) -> LineScanner:
    """Inverse of :func:`scanner_to_dict`.

    Parameters
    ----------
    d : dict

    Returns
    -------
    LineScanner
    """
    d = dict(d)
    orbit = Orbit(**d.pop("orbit"))
    return LineScanner(orbit=orbit, deviations=np.asarray(d.pop("deviations"), dtype=np.float64), **d)


class MapGround:
    """An ECEF sensor model seen from map ground ``(E, N, h)`` in a projected CRS.

    Parameters
    ----------
    inner : SensorModel
        A model of ECEF ground points (:class:`LineScannerModel`, :class:`RPCModel`).
    crs_wkt : str
        The map CRS (WKT); heights are ellipsoidal metres.

    Attributes
    ----------
    n_params : int
        The inner model's.
    """

    def __init__(self, inner, crs_wkt: str) -> None:
        self.inner = inner
        self.crs_wkt = crs_wkt
        self.n_params = inner.n_params
        self._t = None

    def __getstate__(self) -> dict:
        return {"inner": self.inner, "crs_wkt": self.crs_wkt}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["inner"], state["crs_wkt"])

    def __repr__(self) -> str:
        return f"MapGround({self.inner!r})"

    def _transformers(self):
        if self._t is None:
            from pyproj import Transformer

            self._t = (Transformer.from_crs(self.crs_wkt, "EPSG:4326", always_xy=True),
                       Transformer.from_crs("EPSG:4326", self.crs_wkt, always_xy=True))
        return self._t

    def to_ecef(self, ground: np.ndarray) -> np.ndarray:
        """ECEF coordinates ``(m, 3)`` of map points ``(m, 3)``.

        Parameters
        ----------
        ground : ndarray, shape (m, 3)
            ``(E, N, h)``.

        Returns
        -------
        ndarray, shape (m, 3)
        """
        g = np.asarray(ground, dtype=np.float64).reshape(-1, 3)
        lon, lat = self._transformers()[0].transform(g[:, 0], g[:, 1])
        return np.column_stack(geodetic_to_ecef(np.deg2rad(lat), np.deg2rad(lon), g[:, 2]))

    def from_ecef(self, ecef: np.ndarray) -> np.ndarray:
        """Map points ``(E, N, h)`` of ECEF coordinates (inverse of :meth:`to_ecef`).

        Parameters
        ----------
        ecef : ndarray, shape (m, 3)

        Returns
        -------
        ndarray, shape (m, 3)
        """
        p = np.asarray(ecef, dtype=np.float64).reshape(-1, 3)
        lat, lon, h = ecef_to_geodetic(p[:, 0], p[:, 1], p[:, 2])
        e, n = self._transformers()[1].transform(np.rad2deg(lon), np.rad2deg(lat))
        return np.column_stack([e, n, h])

    def initial_params(self) -> np.ndarray:
        """The inner model's start values.

        Returns
        -------
        ndarray, shape (n_params,)
        """
        return self.inner.initial_params()

    def project(self, params: np.ndarray, ground: np.ndarray) -> np.ndarray:
        """Scene pixels ``(m, 2)`` of map points ``(m, 3)``.

        Parameters
        ----------
        params : ndarray, shape (n_params,)
        ground : ndarray, shape (m, 3)
            ``(E, N, h)``.

        Returns
        -------
        ndarray, shape (m, 2)
            ``(x, y)``; NaN where the inner model has no solution.
        """
        return self.inner.project(params, self.to_ecef(ground))

    def jacobians(self, params: np.ndarray, ground: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The inner model's Jacobians, the ground one chained through the map -> ECEF conversion.

        Parameters
        ----------
        params : ndarray, shape (n_params,)
        ground : ndarray, shape (m, 3)
            ``(E, N, h)``.

        Returns
        -------
        J_params : ndarray, shape (m, 2, n_params)
        J_ground : ndarray, shape (m, 2, 3)
            ``d(x, y) / d(E, N, h)``.
        """
        g = np.asarray(ground, dtype=np.float64).reshape(-1, 3)
        jp, jg = self.inner.jacobians(params, self.to_ecef(g))
        step = 1.0  # metres: the conversion is smooth over kilometres
        d = np.empty((g.shape[0], 3, 3))
        for k in range(3):
            off = np.zeros(3)
            off[k] = step
            d[:, :, k] = (self.to_ecef(g + off) - self.to_ecef(g - off)) / (2 * step)
        return jp, jg @ d


def scene_sensor(path: str | os.PathLike, kind: str) -> LineScanner | RPC:
    """What a scene carries for a model of ``kind``: its line scanner or its RPC.

    Parameters
    ----------
    path : str or PathLike
        The scene (GeoTIFF, or a Zarr store written by ``geocoder simulate``).
    kind : {"linescanner", "rpc"}

    Returns
    -------
    LineScanner or RPC

    Raises
    ------
    InputError
        Naming the scene when it carries nothing the model needs.
    """
    spath = os.fspath(path)
    tags: dict[str, Any] = {}
    rpc = None
    if os.path.isdir(spath) or spath.rstrip("/").endswith(".zarr"):
        import zarr

        attrs = dict(zarr.open_group(spath, mode="r").attrs)
        if attrs.get("sensor_class") == "LineScanner":
            tags[LINESCANNER_TAG] = attrs["sensor"]
    else:
        import warnings

        import rasterio
        from rasterio.errors import NotGeoreferencedWarning

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)  # a raw scanner image, on purpose
            with rasterio.open(spath) as src:
                tags = src.tags()
                rpc = src.rpcs
    if kind == "linescanner":
        if LINESCANNER_TAG not in tags:
            raise InputError(spath, f"carries no line-scanner model (GeoTIFF tag {LINESCANNER_TAG} or a `geocoder simulate` "
                                    "satellite store); use --model polynomial or rpc")
        try:
            return scanner_from_dict(json.loads(tags[LINESCANNER_TAG]))
        except (ValueError, TypeError, KeyError) as exc:
            raise InputError(spath, f"has an unreadable line-scanner model ({exc})") from exc
    if kind == "rpc":
        if rpc is None:
            raise InputError(spath, "carries no RPC metadata; use --model polynomial or linescanner")
        return RPC.from_rasterio(rpc)
    raise ValueError(f"kind must be 'linescanner' or 'rpc', got {kind!r}")


def sensor_model(kind: str, sensor: LineScanner | RPC, crs_wkt: str) -> MapGround:
    """The adjustable model of a scene's sensor on map ground.

    Parameters
    ----------
    kind : {"linescanner", "rpc"}
    sensor : LineScanner or RPC
        From :func:`scene_sensor`.
    crs_wkt : str
        The mosaic's CRS.

    Returns
    -------
    MapGround
        A line scanner with :data:`LINESCANNER_FREE` adjusted, or the RPC with an affine
        bias compensation (6 parameters, zero at the start).
    """
    if kind == "linescanner":
        return MapGround(LineScannerModel(sensor, np.array(LINESCANNER_FREE)), crs_wkt)
    return MapGround(RPCModel(sensor), crs_wkt)


def model_to_dict(model, params: np.ndarray) -> dict:
    """A mosaic scene's adjusted model as JSON-serialisable values.

    Parameters
    ----------
    model : MapPolynomial or MapGround
    params : ndarray

    Returns
    -------
    dict
        ``kind`` and what rebuilds it (:func:`model_from_dict`), ``params``.
    """
    p = np.asarray(params, dtype=np.float64).tolist()
    if isinstance(model, MapPolynomial):
        return {"kind": "polynomial", "order": model.order, "origin": model.origin[:2].tolist(), "scale": model.scale,
                "params": p}
    inner = model.inner
    if isinstance(inner, LineScannerModel):
        return {"kind": "linescanner", "crs": model.crs_wkt, "scanner": scanner_to_dict(inner.template),
                "free": np.flatnonzero(inner.free).tolist(), "params": p}
    return {"kind": "rpc", "crs": model.crs_wkt, "rpc": inner.rpc.to_dict(), "params": p}


def model_from_dict(d: dict) -> tuple[Any, np.ndarray]:
    """Inverse of :func:`model_to_dict` (a mosaic written before models had kinds is polynomial).

    Parameters
    ----------
    d : dict

    Returns
    -------
    tuple
        ``(model, params)``.
    """
    kind = d.get("kind", "polynomial")
    params = np.asarray(d["params"], dtype=np.float64)
    if kind == "polynomial":
        return MapPolynomial(d["order"], tuple(d["origin"]), d["scale"]), params
    if kind == "linescanner":
        inner = LineScannerModel(scanner_from_dict(d["scanner"]), np.asarray(d["free"], dtype=np.int64))
    else:
        inner = RPCModel(RPC(**d["rpc"]))
    return MapGround(inner, d["crs"]), params
