"""The registration report's figures: matplotlib (Agg) drawings of arrays already computed.

Every function takes ``plt`` (from :func:`geocoder.reporting.require_matplotlib`), the PNG path
and plain numpy data, draws one figure, saves it and closes it. No arithmetic beyond scaling
for display, no file reading.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .analysis import AlongTrack

DPI = 90


def _save(plt, fig, path: Path) -> None:
    fig.tight_layout()
    # "tight" keeps what tight_layout leaves out, such as the status legend beside its axes
    fig.savefig(path, dpi=DPI, bbox_inches="tight", pad_inches=0.1)
    plt.close(fig)


def _extent(shape: tuple[int, int], factor: int, origin: tuple[int, int] = (0, 0)) -> tuple[float, float, float, float]:
    """imshow extent in full-resolution pixel coordinates (centres at integers)."""
    h, w = shape
    r0, c0 = origin
    return (c0 - 0.5, c0 + w * factor - 0.5, r0 + h * factor - 0.5, r0 - 0.5)


def _limit(*arrays: np.ndarray, q: float = 99.0) -> float:
    values = np.concatenate([np.abs(a[np.isfinite(a)]).ravel() for a in arrays])
    return float(np.percentile(values, q)) if values.size else 1.0


def hsi_figure(plt, path: Path, panels: list[tuple[str, np.ndarray, np.ndarray]], origin: tuple[int, int]) -> None:
    """Saturation (top) and intensity (bottom) of each composite, side by side.

    Nodata is white in saturation (the seed's convention: outside the overlap and failed
    registration appear white).

    Parameters
    ----------
    plt : module
        ``matplotlib.pyplot``.
    path : Path
        The PNG to write.
    panels : list of tuple
        ``(title, saturation, intensity)`` per composite.
    origin : tuple of int
        Full-resolution ``(row, column)`` of the window's first pixel.
    """
    n = len(panels)
    fig, axes = plt.subplots(2, n, figsize=(4.2 * n, 8.4), squeeze=False)
    grey = plt.get_cmap("gray").with_extremes(bad="white")
    for k, (title, sat, inten) in enumerate(panels):
        ext = _extent(sat.shape, 1, origin)
        for row, (img, name) in enumerate(((sat, "saturation"), (inten, "intensity"))):
            ax = axes[row, k]
            ax.imshow(np.ma.masked_invalid(img), cmap=grey, vmin=0, vmax=1 if row == 0 else np.nanmax(inten),
                      extent=ext, interpolation="nearest")
            ax.set_title(f"{title}: {name}", fontsize=10)
            ax.set_xlabel("column (px)")
            ax.set_ylabel("row (px)")
    _save(plt, fig, path)


def maps_figure(plt, path: Path, panels: list[tuple[str, np.ndarray]], factor: int, *,
                symmetric: bool | list[bool], cmap: str | list[str], unit: str = "px") -> None:
    """One colour map per panel (``(title, image)``) on the level grid, in full-resolution pixels.

    A symmetric panel spans +-(99th percentile of |value|), the others 0 .. that percentile.

    Parameters
    ----------
    plt : module
        ``matplotlib.pyplot``.
    path : Path
        The PNG to write.
    panels : list of tuple
        ``(title, image)`` on the level grid.
    factor : int
        Full-resolution pixels per level pixel.
    symmetric : bool or list of bool
        For all panels or one per panel.
    cmap : str or list of str
        Colour map name(s), for all panels or one per panel.
    unit : str
        Colour-bar label.
    """
    n = len(panels)
    symmetric = symmetric if isinstance(symmetric, list) else [symmetric] * n
    cmap = cmap if isinstance(cmap, list) else [cmap] * n
    fig, axes = plt.subplots(1, n, figsize=(5.0 * n, 4.6), squeeze=False)
    for ax, (title, img), sym, name in zip(axes[0], panels, symmetric, cmap):
        lim = _limit(img) or 1e-6
        cm = plt.get_cmap(name).with_extremes(bad="#dddddd")
        kw = {"vmin": -lim, "vmax": lim} if sym else {"vmin": 0, "vmax": lim}
        im = ax.imshow(np.ma.masked_invalid(img), cmap=cm, extent=_extent(img.shape, factor), interpolation="nearest", **kw)
        fig.colorbar(im, ax=ax, shrink=0.8, label=unit)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("column (px)")
        ax.set_ylabel("row (px)")
    _save(plt, fig, path)


#: Colours of the status codes (outside, matched, filled, blunder, no texture, model, estimated).
STATUS_COLOURS = ["#ffffff", "#2c7bb6", "#abd9e9", "#d7191c", "#fdae61", "#999999", "#ffffbf"]


def status_figure(plt, path: Path, status: np.ndarray, legend: dict[int, str], factor: int) -> None:
    """The status map with a legend of the store's ``flag_meanings``.

    Parameters
    ----------
    plt : module
        ``matplotlib.pyplot``.
    path : Path
        The PNG to write.
    status : numpy.ndarray
        Status codes on the level grid.
    legend : dict
        Code -> name.
    factor : int
        Full-resolution pixels per level pixel.
    """
    from matplotlib.colors import BoundaryNorm, ListedColormap
    from matplotlib.patches import Patch

    codes = sorted(legend)
    top = max(codes + [int(np.max(status, initial=0))]) + 1
    colours = [STATUS_COLOURS[c % len(STATUS_COLOURS)] for c in range(top)]
    fig, ax = plt.subplots(figsize=(7.5, 6))
    ax.imshow(status, cmap=ListedColormap(colours), norm=BoundaryNorm(np.arange(top + 1) - 0.5, top),
              extent=_extent(status.shape, factor), interpolation="nearest")
    total = max(status.size, 1)
    handles = [Patch(facecolor=colours[c], edgecolor="black", label=f"{c} {legend[c]} ({np.mean(status == c):.1%})")
               for c in codes if np.any(status == c) or c < top]
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9, title=f"{total} level pixels")
    ax.set_title("status: what each displacement rests on", fontsize=10)
    ax.set_xlabel("column (px)")
    ax.set_ylabel("row (px)")
    _save(plt, fig, path)


def along_track_figure(plt, path: Path, results: dict[str, AlongTrack], truth: dict[str, AlongTrack] | None = None) -> None:
    """Per-line mean displacement after the polynomial (left) and its power spectrum (right).

    Parameters
    ----------
    plt : module
        ``matplotlib.pyplot``.
    path : Path
        The PNG to write.
    results : dict
        Component name -> :class:`AlongTrack`.
    truth : dict, optional
        The same analysis of the true displacement, drawn in red.
    """
    fig, axes = plt.subplots(len(results), 2, figsize=(12, 3.6 * len(results)), squeeze=False)
    for row, (name, at) in enumerate(results.items()):
        ax = axes[row, 0]
        lines = np.arange(at.mean.size)
        ax.plot(lines, at.mean, lw=0.8, color="tab:blue", label="matches")
        if truth is not None and name in truth:
            ax.plot(lines, truth[name].mean, lw=0.8, color="tab:red", alpha=0.7, label="truth")
            ax.legend(fontsize=8)
        band = np.sqrt(at.noise_variance)
        ax.fill_between(lines, at.mean - band, at.mean + band, color="tab:blue", alpha=0.2, lw=0)
        ax.set_xlabel("scan line (row)")
        ax.set_ylabel(f"mean {name} after the polynomial (px)")
        ax.set_title(f"{name}: line means ({at.coverage:.0%} of the lines have matches)", fontsize=10)
        ax = axes[row, 1]
        if at.frequency.size:
            ax.loglog(at.frequency, at.power, lw=0.5, color="0.6", label="periodogram")
            ax.loglog(at.frequency, at.smoothed, lw=1.2, color="tab:blue", label="smoothed")
            if truth is not None and name in truth and truth[name].frequency.size:
                ax.loglog(truth[name].frequency, truth[name].smoothed, lw=1.0, color="tab:red", alpha=0.7,
                          label="truth (smoothed)")
            if np.isfinite(at.floor) and at.floor > 0:
                ax.axhline(at.floor, color="tab:red", ls="--", lw=1, label=f"noise floor (sigma) {at.floor:.2e} px²")
            if np.isfinite(at.tail) and at.tail > 0:
                ax.axhline(at.tail, color="tab:orange", ls=":", lw=1, label=f"spectrum tail {at.tail:.2e} px²")
            if np.isfinite(at.noise_frequency):
                ax.axvline(at.noise_frequency, color="black", lw=1,
                           label=f"noise above {at.noise_frequency:.3f} cycles/line")
            ax.legend(fontsize=8)
        ax.set_xlabel("line frequency (cycles per line)")
        ax.set_ylabel("power (px²)")
        ax.set_title(f"{name}: power spectrum of the line means", fontsize=10)
    _save(plt, fig, path)


def histogram_figure(plt, path: Path, areas: list[tuple[str, np.ndarray, np.ndarray]]) -> None:
    """Grey-level histograms of each area: distorted (raw) and registered (seed 003 Figure 8).

    Parameters
    ----------
    plt : module
        ``matplotlib.pyplot``.
    path : Path
        The PNG to write.
    areas : list of tuple
        ``(title, raw values, registered values)``.
    """
    n = len(areas)
    cols = min(n, 3)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.5 * cols, 3.4 * rows), squeeze=False)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    for ax, (title, raw, reg) in zip(axes.ravel(), areas):
        both = np.concatenate([raw[np.isfinite(raw)], reg[np.isfinite(reg)]])
        if both.size == 0:
            ax.set_title(f"{title}: no data", fontsize=10)
            continue
        bins = np.linspace(both.min(), both.max() + 1e-9, 41)
        ax.hist(raw[np.isfinite(raw)], bins=bins, histtype="step", lw=1.4, color="tab:orange", label="distorted (raw)")
        ax.hist(reg[np.isfinite(reg)], bins=bins, histtype="step", lw=1.4, color="tab:blue", label="registered")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("grey value")
        ax.set_ylabel("pixels")
        ax.legend(fontsize=8)
    _save(plt, fig, path)


def tiepoint_figure(plt, path: Path, background: np.ndarray | None, factor: int, points: dict[str, np.ndarray],
                    shape: tuple[int, int]) -> float:
    """Tie-point residual vectors against the polynomial over a grey background.

    Parameters
    ----------
    plt : module
        ``matplotlib.pyplot``.
    path : Path
        The PNG to write.
    background : numpy.ndarray or None
        Grey image on the level grid.
    factor : int
        Full-resolution pixels per level pixel.
    points : dict
        ``base_x``, ``base_y``, ``residual_x``, ``residual_y``, ``inlier`` arrays.
    shape : tuple of int
        Full-resolution ``(rows, columns)``.

    Returns
    -------
    float
        How many times longer the arrows are drawn.
    """
    fig, ax = plt.subplots(figsize=(8, 7))
    h, w = shape
    if background is not None and np.isfinite(background).any():
        lo, hi = np.nanpercentile(background, [2, 98])
        ax.imshow(np.ma.masked_invalid(background), cmap="gray", vmin=lo, vmax=hi, extent=_extent(background.shape, factor),
                  interpolation="nearest")
    x, y, rx, ry = (points[k] for k in ("base_x", "base_y", "residual_x", "residual_y"))
    inlier = points["inlier"].astype(bool)
    length = np.hypot(rx, ry)
    longest = float(np.nanmax(length[inlier])) if inlier.any() else float(np.nanmax(length, initial=1.0))
    scale = 0.05 * max(h, w) / max(longest, 1e-6)
    for mask, colour, label in ((inlier, "cyan", "kept"), (~inlier, "red", "rejected")):
        if mask.any():
            ax.quiver(x[mask], y[mask], rx[mask] * scale, ry[mask] * scale, angles="xy", scale_units="xy", scale=1,
                      color=colour, width=0.003, label=f"{label} ({int(mask.sum())})")
            ax.plot(x[mask], y[mask], ".", color=colour, ms=2)
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.legend(fontsize=9, loc="upper right")
    ax.set_title(f"tie-point residuals against the polynomial, drawn x{scale:.0f}", fontsize=10)
    ax.set_xlabel("base column (px)")
    ax.set_ylabel("base row (px)")
    _save(plt, fig, path)
    return scale
