"""Library options: :func:`set_options` (global or as a context manager) and :func:`get_option`.

Configuration comes in layers, the first one that says something wins:

1. the parameters of a call (``register(..., tile=256)``, ``RegisterOptions(tile=256)``);
2. :func:`set_options` (``with geocoder.set_options(tile=256): ...``);
3. Dask's configuration, key ``geocoder.<name>`` (YAML or environment, e.g.
   ``DASK_GEOCODER__TILE=256``), for deployments;
4. the defaults in :data:`DEFAULTS`.

Options are read in the process that builds the job (the client), not on the workers.

=============  ===========================================================================
``tile``       default tile (chunk) size of ``register`` and ``ingest``: a multiple of 64
               (default 512)
``progress``   progress bars of ``register`` on standard error: True, False, or None to
               keep the caller's display (the CLI's bars; nothing in a library call)
``n_workers``  worker processes of the local cluster geocoder starts when no client or
               scheduler is given (default: one per CPU)
=============  ===========================================================================
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Self

import dask

#: Built-in defaults (the last layer).
DEFAULTS: dict[str, Any] = {"tile": 512, "progress": None, "n_workers": None}

_OPTIONS: dict[str, Any] = {name: None for name in DEFAULTS}


def _is_tile(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 64 and value % 64 == 0


def _is_workers(value: Any) -> bool:
    return value is None or (isinstance(value, int) and not isinstance(value, bool) and value >= 1)


_VALID: dict[str, tuple[Callable[[Any], bool], str]] = {
    "tile": (_is_tile, "a positive multiple of 64"),
    "progress": (lambda v: v is None or isinstance(v, bool), "True, False or None"),
    "n_workers": (_is_workers, "an integer >= 1 or None"),
}


def _check(name: str, value: Any, *, label: str | None = None) -> None:
    if name not in _VALID:
        raise ValueError(f"{name!r} is not a geocoder option; the options are {', '.join(sorted(_VALID))}")
    valid, what = _VALID[name]
    if name == "tile" and value is None:
        return  # None: back to the next layer
    if not valid(value):
        raise ValueError(f"{label or f'geocoder option {name!r}'} must be {what}, not {value!r}")


class set_options:
    """Set library options globally, or for a ``with`` block.

    Parameters
    ----------
    **options
        ``tile`` (int, multiple of 64), ``progress`` (bool or None), ``n_workers``
        (int >= 1 or None). ``None`` returns an option to the next layer (Dask
        configuration ``geocoder.<name>``, then the default).

    Raises
    ------
    ValueError
        For an unknown option or an invalid value; the message names the option.

    Examples
    --------
    >>> import geocoder
    >>> with geocoder.set_options(tile=256, progress=True):
    ...     geocoder.get_option("tile")
    256
    >>> _ = geocoder.set_options(n_workers=4)  # globally, until set again
    >>> _ = geocoder.set_options(n_workers=None)
    """

    def __init__(self, **options: Any) -> None:
        for name, value in options.items():
            _check(name, value)
        self._previous = {name: _OPTIONS[name] for name in options}
        _OPTIONS.update(options)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        _OPTIONS.update(self._previous)


def get_option(name: str) -> Any:
    """The value of option ``name``: set by :func:`set_options`, else Dask config, else default.

    Parameters
    ----------
    name : str
        ``"tile"``, ``"progress"`` or ``"n_workers"``.

    Returns
    -------
    object
        The value in force.

    Raises
    ------
    ValueError
        For an unknown name, or an invalid value in Dask's configuration (``geocoder.<name>``).
    """
    if name not in DEFAULTS:
        raise ValueError(f"{name!r} is not a geocoder option; the options are {', '.join(sorted(DEFAULTS))}")
    if _OPTIONS[name] is not None:
        return _OPTIONS[name]
    configured = dask.config.get(f"geocoder.{name}", None)
    if configured is not None:
        _check(name, configured, label=f"Dask configuration geocoder.{name}")
        return configured
    return DEFAULTS[name]


#: The tile :func:`default_tile` gives a large scene, and the smaller side (px) from which a scene is large.
LARGE_TILE = 1024
LARGE_SCENE = 2048


def default_tile(shape: tuple[int, int]) -> int:
    """The tile of a job on a scene of ``shape`` (rows, cols) that is given none.

    The option ``tile`` when :func:`set_options` or Dask's configuration sets it; else the
    default 512, or :data:`LARGE_TILE` (1024) when the scene's smaller side is at least
    :data:`LARGE_SCENE` (2048) px. A larger tile pays the halos (lattice, every-pixel pass,
    line estimates) and the per-task costs on fewer tiles, but a scene of a few tiles leaves
    workers idle: with 2 workers the dense job took 7.4-7.7 s at tile 1024 against 8.9-9.6 s
    at 512 on 2048², 111 s against 133 s on 8192², but 4.2-4.5 s against 2.9-3.2 s on 1024²
    (issue 12's notes).

    Parameters
    ----------
    shape : tuple of int
        The scene's rows and columns.

    Returns
    -------
    int
    """
    if _OPTIONS["tile"] is not None or dask.config.get("geocoder.tile", None) is not None:
        return get_option("tile")
    return LARGE_TILE if min(shape) >= LARGE_SCENE else get_option("tile")


def get_options() -> dict[str, Any]:
    """All options with the values in force (see :func:`get_option`).

    Returns
    -------
    dict
        Option name -> value.
    """
    return {name: get_option(name) for name in DEFAULTS}
