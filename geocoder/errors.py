"""Exceptions and warnings raised by geocoder."""

from __future__ import annotations


class GeocoderError(Exception):
    """Base class of every error geocoder raises on purpose.

    The message is a single line that names the file (when there is one) and
    the problem, so the CLI can print it as it is.
    """


class InputError(GeocoderError):
    """An input file is missing, unreadable or unusable (no texture, no overlap)."""

    def __init__(self, path: object, problem: str) -> None:
        self.path = str(path) if path is not None else None
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)


class MatchingError(GeocoderError):
    """The images could not be matched (too few tie points, no overlap)."""


class GeocoderWarning(UserWarning):
    """Warnings from geocoder itself (raised as errors in the test-suite)."""
