"""geocoder: tile-parallel sub-pixel registration and geocoding of scanner imagery on Dask.

The functions that run jobs (:func:`register`, :func:`compose`, :func:`ingest`, :func:`report`,
...) are imported on first use, so that ``import geocoder`` (and the command line's help and
usage errors) does not load the whole pipeline, its kernels and their libraries.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from . import accessor  # noqa: F401  (registers the .geocoder accessor on DataArray and Dataset)
from ._version import __version__
from .errors import GeocoderError, InputError, MatchingError
from .options import get_option, get_options, set_options
from .status import Status

if TYPE_CHECKING:
    from .pipeline.compose import compose
    from .pipeline.register import RegisterOptions, register
    from .reporting import report
    from .scene import ingest, open_scene

#: Public names imported on first use, and the module that holds each.
_LAZY = {
    "compose": ".pipeline.compose",
    "RegisterOptions": ".pipeline.register",
    "register": ".pipeline.register",
    "report": ".reporting",
    "ingest": ".scene",
    "open_scene": ".scene",
}

__all__ = [
    "GeocoderError",
    "InputError",
    "MatchingError",
    "RegisterOptions",
    "Status",
    "__version__",
    "compose",
    "get_option",
    "get_options",
    "ingest",
    "open_scene",
    "register",
    "report",
    "set_options",
]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name], __name__), name)
        globals()[name] = value  # later look-ups do not come here
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})
