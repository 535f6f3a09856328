"""The report of a registration: a self-contained HTML page with PNG figures (seed 003 sec. 8-9).

``geocoder report OUT.zarr --out REPORT_DIR`` and :func:`report` write ``report.html`` and the
figures beside it (relative links, no network needed to view it):

* the HSI check (RGB = base, registered, registered in hue-saturation-intensity) beside the
  polynomial-only composite and a 1-pixel-shifted control (the seed's Figure 5);
* the distortion disparity maps after the polynomial, the status and sigma maps;
* the along-track analysis: per scan line the mean displacement after the polynomial, its
  power spectrum and the line frequency above which it is matching noise;
* the grey-level statistics of five areas before and after registration (Table 3, Figure 8);
* the tie-point residuals, the coarse alignment and the summary;
* with a truth field, the error map and the sigma calibration per status.

Modules: :mod:`.analysis` (pure numpy), :mod:`.source` (reading the store, overview levels,
Dask reductions), :mod:`.figures` (matplotlib), :mod:`.page` (HTML), :mod:`.run` (the sections).
"""

from __future__ import annotations

from ..errors import EnvironmentFailure

__all__ = ["report", "require_matplotlib"]


def require_matplotlib():
    """matplotlib's pyplot on the Agg backend, or a clear error naming the extra to install.

    Returns
    -------
    module
        ``matplotlib.pyplot``.

    Raises
    ------
    EnvironmentFailure
        If matplotlib is not installed.
    """
    try:
        import matplotlib
    except ImportError:
        raise EnvironmentFailure("matplotlib", "geocoder's reports draw their figures with matplotlib, which is not "
                                               "installed; install the report extra: pip install 'geocoder[report]'") from None
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


from .run import report
