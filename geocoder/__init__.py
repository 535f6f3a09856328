"""geocoder: tile-parallel sub-pixel registration and geocoding of scanner imagery on Dask."""

from importlib.metadata import PackageNotFoundError, version

from . import accessor  # noqa: F401  (registers the .geocoder accessor on DataArray and Dataset)
from .errors import GeocoderError, InputError, MatchingError
from .options import get_option, get_options, set_options
from .pipeline.compose import compose
from .pipeline.register import RegisterOptions, register
from .reporting import report
from .scene import ingest, open_scene
from .status import Status

try:
    __version__ = version("geocoder")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0"

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
