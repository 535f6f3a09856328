"""Exceptions and warnings raised by geocoder, and the exit code the CLI gives each."""

from __future__ import annotations

#: Exit codes of the command line (documented in the README).
EXIT_INPUT = 2  # bad input or usage: a rerun with the same arguments fails the same way
EXIT_ENVIRONMENT = 3  # the machine or the cluster failed (disk full, scheduler lost, output busy)
EXIT_INTERRUPTED = 130  # Ctrl-C; an interrupted job keeps its finished work for a rerun


import errno as _errno

#: OSError numbers that mean the machine failed, not the input: the job can resume once fixed.
ENVIRONMENT_ERRNOS = frozenset({_errno.ENOSPC, _errno.EDQUOT, _errno.EIO, _errno.EROFS, _errno.ENOMEM})


class GeocoderError(Exception):
    """Base class of every error geocoder raises on purpose.

    The message is a single line that names the file (when there is one) and
    the problem, so the CLI can print it as it is.

    Attributes
    ----------
    exit_code : int
        The command line's exit code for this error: 2 (:data:`EXIT_INPUT`, bad input or
        usage) unless a subclass says otherwise.
    """

    exit_code = EXIT_INPUT


class InputError(GeocoderError):
    """An input file is missing, unreadable or unusable (no texture, no overlap).

    The message is ``"<path>: <problem>"``, or the problem alone without a path.

    Parameters
    ----------
    path : object
        The file (or URL) at fault, or None when there is none to name.
    problem : str
        What is wrong with it, one line.

    Attributes
    ----------
    path : str or None
        ``str(path)``, or None.
    problem : str
        As given.
    exit_code : int
        2 (:data:`EXIT_INPUT`).
    """

    def __init__(self, path: object, problem: str) -> None:
        self.path = str(path) if path is not None else None
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)


class OutputError(InputError):
    """An output location that geocoder refuses to write (it would replace or hide data)."""


class MatchingError(GeocoderError):
    """The images could not be matched (too few tie points, no overlap).

    Attributes
    ----------
    exit_code : int
        2 (:data:`EXIT_INPUT`): the same inputs fail the same way again.
    """


class EnvironmentFailure(GeocoderError):
    """The machine or the cluster failed: disk full, scheduler lost, output held by another job.

    Not the input's fault: a rerun after the cause is fixed resumes the job.
    """

    exit_code = EXIT_ENVIRONMENT

    def __init__(self, resource: object, problem: str) -> None:
        self.resource = str(resource) if resource is not None else None
        self.problem = problem
        super().__init__(f"{self.resource}: {problem}" if self.resource else problem)


def as_environment_failure(exc: BaseException, resource: object) -> EnvironmentFailure | None:
    """``exc`` as an :class:`EnvironmentFailure` naming ``resource`` if the machine failed (disk full ...)."""
    if isinstance(exc, OSError) and exc.errno in ENVIRONMENT_ERRNOS:
        where = exc.filename or resource
        return EnvironmentFailure(where, f"{exc.strerror or exc}; free the resource and run the same command again to resume")
    return None


class GeocoderWarning(UserWarning):
    """Warnings from geocoder itself (raised as errors in the test-suite)."""
