"""Sensor models for block adjustment: 2-D polynomials, a rigorous line scanner, RPCs.

Every model maps ECEF ground coordinates (metres, shape ``(m, 3)``) to image
coordinates ``(x = column, y = row)`` (shape ``(m, 2)``; pixel centres at
integers, see ``CONVENTIONS.md``) through a parameter vector, and follows the
:class:`SensorModel` protocol consumed by the solver (``n_params``, ``project``,
``jacobians``; :mod:`geocoder.adjust.sensor`).  Every model here also has
``initial_params() -> (n_params,)``, ``param_steps`` (central-difference step per
parameter; a natural scale for each parameter that moves the image by roughly
0.01 px) and ``ground_step`` (metres).  Models without analytic Jacobians use
:func:`geocoder.adjust.sensor.central_difference`, vectorised over points and
looping only over the parameters and the three ground coordinates.

One module per model, all names gathered here
(``from geocoder.adjust.models import LineScannerModel``):

:class:`Polynomial2D`, :class:`MapPolynomial` (:mod:`~geocoder.adjust.models.polynomial`)
    Classic 2-D rectification: ground -> local tangent plane (east, north) at
    an origin, height ignored -> image by polynomials of order 1..3; or from
    map coordinates (the mosaic's per-scene model).
:class:`LineScannerModel` (:mod:`~geocoder.adjust.models.linescanner`)
    Wraps :class:`geocoder.adjust.linescanner_geometry.LineScanner` (8 orbit/time
    + 24 position/attitude deviation parameters), all or a subset free; exact
    Jacobians (:mod:`geocoder.adjust.linescanner_jacobian`).
:class:`RPCModel`, :class:`RPC`, :func:`fit_rpc` (:mod:`~geocoder.adjust.models.rpc`)
    RPC00B rational polynomial coefficients with an affine bias compensation in
    image space (6 parameters).

Pure numpy; no file I/O (``rasterio`` is imported lazily only by the
:class:`RPC` conversions).
"""

from __future__ import annotations

from ...geodesy import enu_basis as _enu_basis  # noqa: F401 - the name before the split
from ..sensor import SensorModel
from ..sensor import as_ground as _as_ground  # noqa: F401 - the name before the split
from ..sensor import as_params as _as_params  # noqa: F401 - the name before the split
from ..sensor import central_difference as _central_difference  # noqa: F401 - the name before the split
from .linescanner import LINE_SCANNER_PARAMETER_NAMES, LineScannerModel  # noqa: F401 - importable, not in __all__
from .polynomial import MapPolynomial, Polynomial2D  # noqa: F401 - importable, not in __all__
from .rpc import RPC, RPCModel, fit_rpc, rpc_terms

__all__ = [
    "RPC",
    "LineScannerModel",
    "Polynomial2D",
    "RPCModel",
    "SensorModel",
    "fit_rpc",
    "rpc_terms",
]
