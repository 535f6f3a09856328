"""The report of a mosaic: Markdown plus pictures of its overlap graph, adjustment and seams.

:func:`write_report` reads what the mosaic keeps (its ``summary`` attribute, and the image
from an overview level of the store, never the full-resolution mosaic of a large block) and
writes a directory::

    report.md            the tables: scenes and pairs, the adjustment per scene, the seams per pair
    overlap_graph.png    scene footprints on the mosaic's overview, an edge per matched pair
    residuals.png        mean adjustment residual per cell of every scene, as vectors
    seams.png            the seamlines (where ``source`` changes) on the overview
    seam_mismatch.png    per pair: the scenes' disagreement at their tie points and the grey step

The directory is written whole or not at all (a temporary sibling, renamed), and only where
nothing is or where geocoder wrote a report before (:func:`geocoder.outputs.check_output`).
Plotting needs matplotlib (the ``report`` extra); it is imported when a report is written.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import xarray as xr

from .. import storage
from ..errors import InputError
from ..outputs import check_output, commit_output, write_marker
from ..reporting import require_matplotlib
from .compose import NO_SOURCE
from .summary import MosaicSummary

__all__ = ["require_matplotlib", "write_report"]

#: The product name of a report directory (its marker file).
PRODUCT = "mosaic-report"


def _overview(source, max_size: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Mosaic (first band, or three) and ``source`` of the coarsest level whose larger side
    still reaches ``max_size`` (or the root, strided if it is an in-memory dataset larger than
    that), and its factor to full resolution."""
    if isinstance(source, xr.Dataset):
        ds = source
        levels = []
    else:
        ds = xr.open_zarr(source, consolidated=False)
        layout = ds.attrs.get("multiscales", {}).get("layout", [])
        levels = [(2**k, item["asset"]) for k, item in enumerate(layout) if k]
    h, w = ds.sizes["y"], ds.sizes["x"]
    factor, group = 1, None
    for f, asset in levels:  # the coarsest level still at least max_size (the root if the mosaic is smaller)
        if max(h, w) / f >= max_size:
            factor, group = f, asset
    level = xr.open_zarr(source, group=group, consolidated=False) if group is not None else ds
    step = max(1, math.ceil(max(level.sizes["y"], level.sizes["x"]) / max_size)) if group is None else 1
    bands = level.sizes["band"]
    image = np.asarray(level["mosaic"][: 3 if bands >= 3 else 1, ::step, ::step].values, dtype=np.float32)
    src = np.asarray(level["source"][::step, ::step].values)
    return image, src, factor * step


def _show(ax, image: np.ndarray, factor: int) -> None:
    """The overview on axes in full-resolution output pixels (grey, or RGB stretched 2-98 %)."""
    h, w = image.shape[1:]
    extent = (-0.5, w * factor - 0.5, h * factor - 0.5, -0.5)
    finite = np.isfinite(image)
    if not finite.any():
        return
    lo, hi = np.percentile(image[finite], [2, 98])
    scaled = np.clip((image - lo) / max(hi - lo, 1e-12), 0, 1)
    if image.shape[0] == 3:
        rgba = np.concatenate([np.moveaxis(np.nan_to_num(scaled), 0, -1), np.all(finite, axis=0)[..., None]], axis=-1)
        ax.imshow(rgba, extent=extent, interpolation="nearest")
    else:
        ax.imshow(np.ma.masked_invalid(scaled[0]), cmap="gray", extent=extent, interpolation="nearest", vmin=0, vmax=1)
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_xlabel("output column (px)")
    ax.set_ylabel("output row (px)")


def _outline(ax, points: list, **kw) -> None:
    p = np.asarray(points + points[:1], dtype=float)
    ax.plot(p[:, 0], p[:, 1], **kw)


def _figure_overlap(plt, path: Path, s: MosaicSummary, image: np.ndarray, factor: int) -> None:
    fig, ax = plt.subplots(figsize=(8, 8))
    _show(ax, image, factor)
    index = {k: n for n, k in enumerate(s.block)}
    centres = {k: np.mean(np.asarray(s.footprints[n], float), axis=0) for k, n in index.items()} if s.footprints else {}
    colours = plt.get_cmap("tab10")
    for k, n in index.items():
        if s.footprints:
            _outline(ax, s.footprints[n], color=colours(n % 10), lw=1.5)
    most = max([p["ties"] for p in s.pairs] or [1]) or 1
    for p in s.pairs:
        if p["i"] in centres and p["j"] in centres:
            a, b = centres[p["i"]], centres[p["j"]]
            style = "-" if p["ties"] else ":"
            ax.plot([a[0], b[0]], [a[1], b[1]], style, color="yellow", lw=0.5 + 3.0 * p["ties"] / most)
            ax.annotate(str(p["ties"]), (a + b) / 2, color="yellow", fontsize=8, ha="center", va="center")
    for k, c in centres.items():
        ax.plot(*c, "o", color="red", ms=5)
        ax.annotate(str(k), c, color="white", fontsize=10, xytext=(4, 4), textcoords="offset points")
    ax.set_title(f"overlap graph: {len(s.block)} scenes, {sum(1 for p in s.pairs if p['ties'])} matched pairs "
                 "(edge width: tie points)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _figure_residuals(plt, path: Path, s: MosaicSummary, image: np.ndarray, factor: int) -> float:
    fig, ax = plt.subplots(figsize=(8, 8))
    _show(ax, image, factor)
    for n, pts in enumerate(s.footprints):
        _outline(ax, pts, color="white", lw=0.8, alpha=0.6)
    bins = np.array([b for per in s.residual_bins for b in per], dtype=float).reshape(-1, 5)
    scale = 1.0
    if bins.size:
        longest = float(np.max(np.hypot(bins[:, 2], bins[:, 3]))) or 1.0
        h, w = image.shape[1:]
        scale = 0.08 * max(h, w) * factor / longest  # the longest vector: 8 % of the mosaic's side
        ax.quiver(bins[:, 0], bins[:, 1], bins[:, 2] * scale, bins[:, 3] * scale, angles="xy", scale_units="xy", scale=1,
                  color="cyan", width=0.003)
        ax.set_title(f"mean residual per cell of every scene (longest {longest:.3f} px, x{scale:.0f})")
    else:
        ax.set_title("no residuals")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return scale


def _figure_seams(plt, path: Path, s: MosaicSummary, image: np.ndarray, src: np.ndarray, factor: int) -> None:
    fig, ax = plt.subplots(figsize=(8, 8))
    _show(ax, image, factor)
    seam = np.zeros(src.shape, bool)
    for a, b in ((src[:, :-1], src[:, 1:]), (src[:-1, :], src[1:, :])):
        hit = (a != b) & (a != NO_SOURCE) & (b != NO_SOURCE)
        seam[: hit.shape[0], : hit.shape[1]] |= hit
    r, c = np.nonzero(seam)
    ax.plot((c + 0.5) * factor - 0.5, (r + 0.5) * factor - 0.5, ",", color="red")
    for pts in s.footprints:
        _outline(ax, pts, color="white", lw=0.6, alpha=0.5)
    ax.set_title(f"seamlines ({s.seam_mode}) on the overview (1:{factor})")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _figure_mismatch(plt, path: Path, s: MosaicSummary) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    names = [f"{p['i']}-{p['j']}" for p in s.seams]
    x = np.arange(len(names))
    axes[0].bar(x, [p.get("tie_mismatch_px", np.nan) for p in s.seams], color="tab:blue")
    axes[0].set_ylabel("RMS disagreement at tie points (px)")
    axes[1].bar(x, [p["grey_step"] for p in s.seams], color="tab:orange")
    axes[1].set_ylabel("RMS grey-value step along the seam")
    for ax in axes:
        ax.set_xticks(x, names, rotation=90 if len(names) > 12 else 0, fontsize=8)
        ax.set_xlabel("pair of scenes")
    fig.suptitle("seam mismatch per pair")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _fmt(v, digits: int = 3) -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{digits}f}"


def _write_points(store: str, path: Path) -> bool:
    """The store's adjusted ground points (group ``points``) as CSV; False if it has none."""
    import zarr

    from .block import POINT_COLUMNS

    try:
        group = zarr.open_group(store, path="points", mode="r")
    except (FileNotFoundError, KeyError, zarr.errors.GroupNotFoundError):
        return False
    table = np.column_stack([np.asarray(group[name][:]) for name in POINT_COLUMNS])
    np.savetxt(path, table, delimiter=",", header=",".join(POINT_COLUMNS), comments="",
               fmt=["%.4f", "%.4f", "%d", "%d", "%.5f", "%.5f", "%.3f"])
    return True


def _markdown(s: MosaicSummary, gains: np.ndarray | None, factor: int, arrow_scale: float,
              has_points: bool = False) -> str:
    name = [os.path.basename(str(v)) for v in s.scenes]
    lines = [
        "# Mosaic report", "",
        (f"{len(s.scenes)} scenes, {len(s.block)} in the block; mosaic {s.shape[0]} x {s.shape[1]} px; "
         f"figures drawn from the overview at 1:{factor}."), "",
        "## Overlap graph", "",
        f"{len(s.pairs)} overlapping pairs, {sum(1 for p in s.pairs if p['ties'])} of them matched; ground points by "
        "number of scenes that see them: " + (", ".join(f"{k}: {v}" for k, v in s.rays.items()) or "-") + ".", "",
        "![overlap graph](overlap_graph.png)", "",
        "| pair | scene i | scene j | tie points | note |", "|---|---|---|---:|---|",
        *(f"| {p['i']}-{p['j']} | {name[p['i']]} | {name[p['j']]} | {p['ties']} | {p.get('problem', '')} |" for p in s.pairs),
        "",
    ]
    if s.georeference_sigma_px is not None:
        lines += [f"No reference orthoimage and no control points: every scene placed by its georeference, and the "
                  f"block controlled by them (a 5 x 5 grid of points per scene, together one position known to "
                  f"{s.georeference_sigma_px:g} px): the mosaic is where the georeferences put it on average.", ""]
    chained = {k: how for k, how in s.placed.items() if how.startswith("via")}
    if chained:
        lines += ["Not found on the reference, placed through a neighbour (no control points of their own):", "",
                  *(f"- scene {k} ({name[int(k)]}): {how}" for k, how in chained.items()), ""]
    if s.left_out:
        lines += ["Left out of the block:", "", *(f"- scene {k} ({name[int(k)]}): {why}" for k, why in s.left_out.items()), ""]
    lines += [
        "## Block adjustment", "",
        (f"sigma0 {_fmt(s.sigma0)}, {s.iterations} iterations. Residual: observed minus adjusted scene pixel; "
         "precision: RMS standard deviation of the adjusted position over the scene's footprint (scene pixels)."), "",
        "| scene | file | control points | observations | RMS residual px | precision px | gain | offset |",
        "|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for n, k in enumerate(s.block):
        g = gains[n, 0] if gains is not None and n < len(gains) else (np.nan, np.nan)
        lines.append(f"| {k} | {name[k]} | {s.control_points[k] if k < len(s.control_points) else '-'} | "
                     f"{s.observations[n] if n < len(s.observations) else '-'} | "
                     f"{_fmt(s.rms_px[n] if n < len(s.rms_px) else None)} | "
                     f"{_fmt(s.precision_px[n] if n < len(s.precision_px) else None, 4)} | {_fmt(float(g[0]), 4)} | "
                     f"{_fmt(float(g[1]), 2)} |")
    lines += ["", "![residuals](residuals.png)", "",
              (f"Vectors: the mean residual of a scene's observations in each of 3 x 3 cells, drawn {arrow_scale:.0f} "
               "times longer."), ""]
    if s.given_residuals:
        lines += [f"Control points from {os.path.basename(s.given_file)} (residual: the scene pixel measured against the "
                  "map position through the adjusted model, scene pixels; check points were withheld from the "
                  "adjustment):", "", "| id | scene | residual px | role |", "|---|---:|---:|---|",
                  *(f"| {pid} | {k} | {_fmt(r, 3)} | {role} |" for pid, k, r, role in s.given_residuals), ""]
    if s.rejected:
        lines += [(f"Observations left out: {s.rejected.get('robust', 0)} by the robust re-weighting, "
                   f"{s.rejected.get('snooping', 0)} by data snooping (Baarda, w > 3.29)."), ""]
    if s.point_sigma_px:
        lines += ["Precision of the adjusted ground points (standard deviation of the map position, the larger axis, "
                  "reference pixels):", "", "| points | median | 95 % | max |", "|---|---:|---:|---:|",
                  *(f"| {k} | {_fmt(v[0], 4)} | {_fmt(v[1], 4)} | {_fmt(v[2], 4)} |" for k, v in s.point_sigma_px.items()),
                  ""]
    if has_points:
        lines += ["Every ground point: [points.csv](points.csv) (map position, control or tie, the scenes that see it, "
                  "sigma_x and sigma_y in reference pixels, the largest normalised residual of its observations).", ""]
    lines += [
        "## Seams", "",
        (f"Seamlines: {s.seam_mode}"
         + (f" ({s.seam_cells_moved} coarse cells moved from the centre rule by the least-cost cut)"
            if s.seam_mode == "least-cost" else "")
         + ". Grey-value step along all seams (RMS difference of the two balanced scenes at the seam): "
         f"{_fmt(s.seam_grey_step, 2)}."), "",
    ]
    if s.seam_step:
        lines += [(f"Radiometric balance: grey-value step at the tie points {_fmt(s.seam_step[0], 2)} before, "
                   f"{_fmt(s.seam_step[1], 2)} after."), ""]
    lines += [
        "![seams](seams.png)", "",
        "| pair | seam length px | grey step (RMS) | grey bias | tie-point mismatch px |", "|---|---:|---:|---:|---:|",
        *(f"| {p['i']}-{p['j']} | {p['pixels']} | {_fmt(p['grey_step'], 2)} | {_fmt(p['grey_bias'], 2)} | "
          f"{_fmt(p.get('tie_mismatch_px'))} |" for p in s.seams),
        "", "![seam mismatch](seam_mismatch.png)", "",
        ("Tie-point mismatch: RMS of the difference of the two scenes' residuals at their common ground points, the "
         "adjustment's estimate of how far apart the two put the same ground point along their seam."), "",
    ]
    if s.seconds:
        lines += ["## Time", "", "| stage | s |", "|---|---:|", *(f"| {k} | {v:.1f} |" for k, v in s.seconds.items()), ""]
    return "\n".join(lines)


def write_report(source, directory: str | os.PathLike, *, overwrite: bool = False, max_size: int = 1024) -> str:
    """Write a mosaic's report: ``report.md`` and its figures.

    Parameters
    ----------
    source : str, PathLike or xarray.Dataset
        A mosaic's Zarr store (read from its overview levels), or the dataset
        :func:`geocoder.mosaic` returned.
    directory : str or PathLike
        The report's directory (local); written atomically, and replaced only if ``overwrite``
        and geocoder wrote it.
    overwrite : bool
        Replace an earlier report there.
    max_size : int
        Larger side (pixels) of the overview the figures show: the smallest overview level
        at least this large.

    Returns
    -------
    str
        The report's directory.
    """
    plt = require_matplotlib()
    store = None if isinstance(source, xr.Dataset) else os.fspath(source)
    final = check_output(directory, inputs=(store,) if store else (), overwrite=overwrite, option="--report")
    if storage.is_url(final):
        raise InputError(final, "a report is written to a local directory")
    if not os.path.isdir(os.path.dirname(final)):
        raise InputError(final, "the report's parent directory does not exist")
    attrs = source.attrs if isinstance(source, xr.Dataset) else xr.open_zarr(store, consolidated=False).attrs
    if "summary" not in attrs:
        raise InputError(store or "dataset", "is not a mosaic (no summary attribute)")
    summary = MosaicSummary(**json.loads(attrs["summary"]))
    gains = np.asarray(json.loads(attrs["radiometry"])) if "radiometry" in attrs else None
    image, src, factor = _overview(source, max_size)
    tmp = storage.temporary_sibling(final)
    os.makedirs(tmp)
    try:
        out = Path(tmp)
        _figure_overlap(plt, out / "overlap_graph.png", summary, image, factor)
        arrow_scale = _figure_residuals(plt, out / "residuals.png", summary, image, factor)
        _figure_seams(plt, out / "seams.png", summary, image, src, factor)
        _figure_mismatch(plt, out / "seam_mismatch.png", summary)
        has_points = store is not None and _write_points(store, out / "points.csv")
        (out / "report.md").write_text(_markdown(summary, gains, factor, arrow_scale, has_points), encoding="utf-8")
        write_marker(tmp, PRODUCT)
        commit_output(tmp, final, overwrite=overwrite)
    except BaseException:
        storage.remove(tmp)
        raise
    return final
