"""The installed geocoder version, in a module that imports nothing else of the package.

:mod:`geocoder.runtime` and the worker preload compare versions of client and workers;
reading it here rather than from the package root keeps them from importing the whole
pipeline for one string.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("geocoder")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0"

__all__ = ["__version__"]
