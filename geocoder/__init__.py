"""geocoder: tile-parallel sub-pixel registration and geocoding of scanner imagery on Dask."""

from . import accessor  # noqa: F401  (registers the .geocoder accessor on DataArray and Dataset)
from ._version import __version__
from .errors import GeocoderError, InputError, MatchingError
from .options import get_option, get_options, set_options
from .pipeline.compose import compose
from .pipeline.register import RegisterOptions, register
from .reporting import report
from .scene import ingest, open_scene
from .status import Status

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
