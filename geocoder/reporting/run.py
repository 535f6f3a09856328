"""``report(store, out)``: gather what the registration report shows and write the page.

Each section is one function: it reads what it needs (:mod:`.source`), computes with the
pure functions of :mod:`.analysis`, draws with :mod:`.figures` and adds its text, tables and
figure to the :class:`.page.Page`. A section whose input is missing (the base image moved,
a store without dense matches) says so on the page instead of failing the report.
"""

from __future__ import annotations

import json
import logging
import os
import warnings
from pathlib import Path

import dask.array as da
import numpy as np
from scipy import ndimage

from .. import storage
from ..errors import InputError
from ..outputs import check_output, commit_output, write_marker
from ..status import Status
from . import analysis, figures
from .page import Page
from .source import (
    Source,
    level_polynomial,
    line_sums,
    open_image,
    open_source,
    read_truth,
    status_sums,
    window,
)

log = logging.getLogger("geocoder")

#: The product name of a report directory (its marker file).
PRODUCT = "register-report"
#: The page's file name.
PAGE = "report.html"


def _default_template_length() -> int:
    """Length (px) along the scan line of the dense matcher's default template."""
    from ..pipeline.dense import DenseOptions

    return 2 * int(DenseOptions().alsc.radius) + 1


class _Context:
    """What the sections share: the output directory, matplotlib, the source and the inputs."""

    def __init__(self, plt, directory: Path, src: Source, page: Page, band: int, base, distorted, hsi_size: int,
                 template_length: int | None = None) -> None:
        self.plt, self.dir, self.src, self.page, self.band = plt, directory, src, page, band
        self.hsi_size = hsi_size
        self.base, self.base_problem = open_image(base or src.summary.get("base"), band=band)
        self.dist, self.dist_problem = open_image(distorted or src.summary.get("distorted"), band=band)
        if self.base is not None and (self.base.sizes["y"], self.base.sizes["x"]) != src.shape:
            self.base, self.base_problem = None, (f"{base or src.summary.get('base')} is {self.base.sizes['x']} x "
                                                  f"{self.base.sizes['y']} px, not the registration's grid")
        self._poly = None
        self._status = None
        self.template_length = template_length or _default_template_length()

    def level(self, name: str) -> np.ndarray | None:
        """A level variable as float64 (first band of a banded one), None if the store lacks it."""
        if name not in self.src.level:
            return None
        var = self.src.level[name]
        if "band" in var.dims:
            var = var.isel(band=min(self.band, var.sizes["band"]) - 1)
        return np.asarray(var.values, dtype=np.float64)

    @property
    def status(self) -> np.ndarray:
        if self._status is None:
            self._status = np.asarray(self.src.level["status"].values)
        return self._status

    @property
    def poly(self):
        if self._poly is None:
            self._poly = level_polynomial(self.src)
        return self._poly

    def registered(self, rows, cols) -> np.ndarray:
        var = self.src.root["registered"]
        return window(var.isel(band=min(self.band, var.sizes["band"]) - 1), rows, cols)


# ----------------------------------------------------------------------------- sections


def _summary_section(ctx: _Context) -> None:
    from ..pipeline.register import RegisterSummary

    s, page = ctx.src, ctx.page
    page.section("summary", "Summary")
    h, w = s.shape
    page.paragraph(f"Registration of {s.summary.get('distorted', '?')} onto {s.summary.get('base', '?')}: "
                   f"{w} x {h} px on the base grid. Maps are drawn from "
                   + (f"overview level 1:{s.factor} ({s.level.sizes['x']} x {s.level.sizes['y']} px)." if s.factor > 1
                      else "the full-resolution grid."))
    known = {k: v for k, v in s.summary.items() if k in RegisterSummary.__dataclass_fields__}
    page.preformatted(RegisterSummary(**known).lines())
    page.section("coarse", "Coarse alignment")
    coarse = json.loads(s.root.attrs["coarse_alignment"]) if "coarse_alignment" in s.root.attrs else None
    if coarse is None:
        page.paragraph("The store does not record its coarse alignment.", missing=True)
    else:
        m = np.asarray(coarse["matrix"], dtype=float)
        page.table(["method", "pyramid level", "peak", "x' = a x + b y + c", "y' = d x + e y + f"],
                   [[str(coarse["method"]), f"1/{coarse['factor']}", coarse["peak"],
                     "a {:.5f}, b {:.5f}, c {:.2f}".format(*m[0]), "d {:.5f}, e {:.5f}, f {:.2f}".format(*m[1])]])
    if s.mapping is not None:
        page.paragraph(f"Global polynomial: order {s.mapping.order}, centre ({s.mapping.centre[0]:.1f}, "
                       f"{s.mapping.centre[1]:.1f}), scale {s.mapping.scale:.1f} px (the store's mapping attribute).")


def _sample_polynomial(ctx: _Context, rows, cols) -> tuple[np.ndarray | None, str | None]:
    """The distorted image sampled once (bilinear) at ``p + poly(p)`` over a base window."""
    if ctx.dist is None:
        return None, f"the distorted image cannot be read: {ctx.dist_problem}"
    if ctx.src.mapping is None:
        return None, "the store has no mapping attribute (the global polynomial)"
    px, py = analysis.polynomial_grid(ctx.src.mapping, np.arange(*cols), np.arange(*rows))
    qx = px + np.arange(*cols)[None, :]
    qy = py + np.arange(*rows)[:, None]
    hd, wd = ctx.dist.sizes["y"], ctx.dist.sizes["x"]
    c0, c1 = int(max(0, np.floor(qx.min()) - 2)), int(min(wd, np.ceil(qx.max()) + 3))
    r0, r1 = int(max(0, np.floor(qy.min()) - 2)), int(min(hd, np.ceil(qy.max()) + 3))
    if c0 >= c1 or r0 >= r1:
        return np.full(qx.shape, np.nan), None
    img = window(ctx.dist, (r0, r1), (c0, c1))
    inside = (qx >= 0) & (qx <= wd - 1) & (qy >= 0) & (qy <= hd - 1)
    out = ndimage.map_coordinates(img, [qy - r0, qx - c0], order=1, mode="nearest")
    return np.where(inside, out, np.nan), None


def _hsi_section(ctx: _Context) -> None:
    page = ctx.page
    page.section("hsi", "HSI check (seed 003 sec. 8)")
    if ctx.base is None:
        page.paragraph(f"The base image is missing, so the HSI check cannot be drawn: {ctx.base_problem}. "
                       "Give it with --base (base= in Python).", missing=True)
        return
    h, w = ctx.src.shape
    sh, sw = min(h, ctx.hsi_size), min(w, ctx.hsi_size)
    rows = ((h - sh) // 2, (h - sh) // 2 + sh)
    cols = ((w - sw) // 2, (w - sw) // 2 + sw)
    base = window(ctx.base, rows, cols)
    reg = ctx.registered(rows, cols)
    panels = []
    poly, problem = _sample_polynomial(ctx, rows, cols)
    composites = {}
    if poly is not None:
        composites["polynomial only"] = poly
    composites["registered"] = reg
    composites["registered, shifted 1 px down and right"] = analysis.shift_image(reg, 1, 1)
    hsis = {k: analysis.hsi_composite(base, v) for k, v in composites.items()}
    common = np.all([np.isfinite(s) for _, s, _ in hsis.values()], axis=0)
    for title, (_, sat, inten) in hsis.items():
        panels.append((title, sat, inten))
    figures.hsi_figure(ctx.plt, ctx.dir / "hsi.png", panels, (rows[0], cols[0]))
    where = "the whole scene" if (sh, sw) == (h, w) else f"the central {sw} x {sh} px window (rows {rows[0]}-{rows[1] - 1}, columns {cols[0]}-{cols[1] - 1}) at full resolution"
    page.paragraph("RGB = (base, registered, registered), each stretched between its 1st and 99th percentile, in "
                   "hue-saturation-intensity. Where the images agree the composite is grey (saturation 0); a "
                   "misregistered edge is a black-and-white fringe in saturation and a blur in intensity. Shown on "
                   f"{where}; nodata is white in saturation.")
    if problem:
        page.paragraph(f"The polynomial-only composite is missing: {problem}. Give the distorted image with "
                       "--distorted (distorted= in Python).", missing=True)
    page.figure("hsi.png", "Saturation (top) and intensity (bottom) of the HSI composite: "
                + ", ".join(hsis) + ".")
    page.table(["composite", "mean saturation", "median saturation", "pixels"],
               [[k, float(np.mean(s[common])) if common.any() else None,
                 float(np.median(s[common])) if common.any() else None, int(common.sum())]
                for k, (_, s, _) in hsis.items()], table_id="hsi-table")
    page.paragraph("Mean saturation over the pixels valid in every composite: the better the registration, the lower; "
                   "the 1-pixel shift is the seed's Figure 5 control.")


def _disparity_section(ctx: _Context) -> None:
    page, src = ctx.page, ctx.src
    page.section("disparity", "Distortion disparity maps (seed 003 sec. 9)")
    status = ctx.status
    outside = status == int(Status.OUTSIDE)
    dx, dy = ctx.level("dx"), ctx.level("dy")
    if ctx.poly is None:
        page.paragraph("The store has no mapping attribute: the maps show the whole displacement.", missing=True)
        rx, ry = dx, dy
    else:
        rx, ry = dx - ctx.poly[0], dy - ctx.poly[1]
    rx, ry = np.where(outside, np.nan, rx), np.where(outside, np.nan, ry)
    figures.maps_figure(ctx.plt, ctx.dir / "disparity.png",
                        [("dx after the polynomial", rx), ("dy after the polynomial", ry),
                         ("magnitude", np.hypot(rx, ry))], src.factor, symmetric=[True, True, False],
                        cmap=["RdBu_r", "RdBu_r", "magma"])
    page.figure("disparity.png", "Displacement after removing the global polynomial (px): dx, dy and the magnitude "
                "(colour scale: 99th percentile of |value|; grey: outside the overlap).")
    matched = status == int(Status.MATCHED)
    rows = []
    for name, code in (("matched", matched), ("all inside", ~outside)):
        if code.any():
            rows.append([name, int(code.sum()), float(np.sqrt(np.nanmean(rx[code] ** 2))),
                         float(np.sqrt(np.nanmean(ry[code] ** 2))), float(np.nanmax(np.hypot(rx, ry)[code]))])
    page.table(["level pixels", "count", "RMS dx after poly", "RMS dy after poly", "max magnitude"], rows)
    page.section("status", "Status and sigma maps")
    figures.status_figure(ctx.plt, ctx.dir / "status.png", status, src.legend, src.factor)
    page.figure("status.png", "Status of every pixel (legend: the store's flag_meanings)" +
                (f", nearest pixel of overview 1:{src.factor}" if src.factor > 1 else "") + ".")
    counts = src.summary.get("status_counts") or {}
    if counts:
        total = sum(counts.values())
        page.table(["status", "pixels", "share"], [[k, int(v), f"{v / total:.1%}"] for k, v in counts.items()])
    if "sigma_x" in src.level:
        figures.maps_figure(ctx.plt, ctx.dir / "sigma.png", [("sigma_x", ctx.level("sigma_x")),
                                                              ("sigma_y", ctx.level("sigma_y"))],
                            src.factor, symmetric=False, cmap="viridis")
        page.figure("sigma.png", "Standard deviation of the matches from the least-squares covariance (px).")
    else:
        page.paragraph("The store has no sigma maps (registered with --no-dense).", missing=True)


def _along_track_section(ctx: _Context, truth) -> dict[str, analysis.AlongTrack]:
    page = ctx.page
    page.section("along-track", "Along-track analysis (seed 003 sec. 9)")
    sums = line_sums(ctx.src)
    if sums is None or sums[:, 2].sum() == 0:
        page.paragraph("No dense matches (registered with --no-dense, or nothing matched): no along-track analysis.",
                       missing=True)
        return {}
    n, nsig = sums[:, 2], sums[:, 5]
    length = ctx.template_length
    with np.errstate(invalid="ignore", divide="ignore"):
        results = {}
        for name, k, ks in (("dx", 0, 3), ("dy", 1, 4)):
            mean = np.where(n > 0, sums[:, k] / n, np.nan)
            # matches of a line share pixels over the template's length: n / length of them are independent
            var = np.where((nsig > 0) & (n > 0), sums[:, ks] / nsig / np.maximum(n / length, 1.0), np.nan)
            results[name] = analysis.line_spectrum(mean, var)
    truth_lines = _truth_lines(ctx, truth) if truth is not None else None
    truth_spectra = ({k: analysis.line_spectrum(v, results[k].noise_variance) for k, v in truth_lines.items()}
                     if truth_lines is not None else None)
    figures.along_track_figure(ctx.plt, ctx.dir / "along_track.png", results, truth_spectra)
    page.paragraph("For every scan line (row), the mean displacement of its matched pixels after the global "
                   "polynomial (a Dask reduction over the full-resolution rows; band: +-1 sigma of the mean), and the "
                   "power spectrum of these line means (gaps interpolated, a straight line removed, Hann window). The "
                   "noise floor is the mean over the lines of sigma^2 / n (the matches' mean squared sigma over their "
                   "number of independent matches); above the frequency where the smoothed spectrum meets it the "
                   "line-to-line energy is matching noise. Neighbouring matches of a line share the pixels of their "
                   f"template, so a line of n matches counts as n / {length} independent ones ({length} px: the "
                   "template's length along the line); the median of the spectrum's highest quarter is shown "
                   "beside the floor." + (" Red: the truth's line means over the same pixels." if truth else ""))
    page.figure("along_track.png", "Per-line mean displacement after the polynomial and its power spectrum.")
    rows = []
    for name, at in results.items():
        lines = at.sampling_lines
        period = 1.0 / at.peak_frequency if at.peak_frequency and np.isfinite(at.peak_frequency) else None
        rows.append([name, at.coverage, float(np.nanstd(at.mean)), period, at.floor, at.tail, at.noise_frequency,
                     "-" if lines is None else str(lines)])
    page.table(["component", "lines with matches", "std of line means px", "peak period (lines)", "noise floor px²",
                "spectrum tail px²", "noise above (cycles/line)", "INS sampling every N lines"], rows,
               table_id="along-track-table")
    for name, at in results.items():
        lines = at.sampling_lines
        if lines is None:
            page.paragraph(f"{name}: the line means are at the noise floor everywhere: no turbulence is measurable.")
        elif at.noise_frequency >= 0.5:
            page.paragraph(f"{name}: the spectrum stays above the noise floor up to the Nyquist frequency: an INS would "
                           "have to sample at least every line (or the floor is underestimated).")
        else:
            page.paragraph(f"{name}: the energy is noise above {at.noise_frequency:.4f} cycles per line "
                           f"(periods shorter than {1 / at.noise_frequency:.1f} lines): an INS would have to sample at "
                           f"least every {lines} lines to model the turbulence.")
    return results


def _truth_lines(ctx: _Context, truth) -> dict[str, np.ndarray]:
    """Per-line mean of the truth after the polynomial, over the matched pixels (Dask reduction)."""
    (tx, ty), _ = truth
    st = ctx.src.root["status"].data
    st = st if isinstance(st, da.Array) else da.from_array(st, chunks=tx.chunks)
    st = st.rechunk(tx.chunks)
    mapping = ctx.src.mapping
    matched = st == int(Status.MATCHED)

    def after_poly(t, component):
        def block(b, block_info=None):
            (r0, r1), (c0, c1) = block_info[0]["array-location"]
            return b - analysis.polynomial_grid(mapping, np.arange(c0, c1), np.arange(r0, r1))[component]
        return t.map_blocks(block, dtype=np.float64)

    n = matched.sum(axis=1)
    sx = da.where(matched, after_poly(tx, 0), 0).sum(axis=1)
    sy = da.where(matched, after_poly(ty, 1), 0).sum(axis=1)
    n, sx, sy = da.compute(n, sx, sy)
    with np.errstate(invalid="ignore", divide="ignore"):
        return {"dx": np.where(n > 0, sx / n, np.nan), "dy": np.where(n > 0, sy / n, np.nan)}


def _areas(h: int, w: int, count: int = 5) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """Square areas: the centre and the centres of the four quadrants (seed 003 Table 3 uses 5 fields)."""
    side = max(8, min(128, min(h, w) // 5))
    centres = [(0.5, 0.5), (0.25, 0.25), (0.25, 0.75), (0.75, 0.25), (0.75, 0.75)][:count]
    out = []
    for fy, fx in centres:
        r0 = int(np.clip(round(fy * h - side / 2), 0, max(h - side, 0)))
        c0 = int(np.clip(round(fx * w - side / 2), 0, max(w - side, 0)))
        out.append(((r0, min(h, r0 + side)), (c0, min(w, c0 + side))))
    return out


def _grey_section(ctx: _Context) -> None:
    page = ctx.page
    page.section("grey", "Grey-level statistics (seed 003 sec. 8, Table 3, Figure 8)")
    if ctx.dist is None:
        page.paragraph(f"The distorted image is missing, so the statistics before registration cannot be computed: "
                       f"{ctx.dist_problem}. Give it with --distorted (distorted= in Python).", missing=True)
        return
    h, w = ctx.src.shape
    hd, wd = ctx.dist.sizes["y"], ctx.dist.sizes["x"]
    rows, hists = [], []
    for k, (rr, cc) in enumerate(_areas(h, w), start=1):
        reg = ctx.registered(rr, cc)
        dx, dy = window(ctx.src.root["dx"], rr, cc), window(ctx.src.root["dy"], rr, cc)
        st = window(ctx.src.root["status"], rr, cc)
        inside = (st != int(Status.OUTSIDE)) & np.isfinite(reg)
        qx = np.rint(dx + np.arange(*cc)[None, :])[inside]
        qy = np.rint(dy + np.arange(*rr)[:, None])[inside]
        ok = (qx >= 0) & (qx < wd) & (qy >= 0) & (qy < hd)
        raw = np.zeros(0)
        if ok.any():
            qx, qy = qx[ok].astype(np.intp), qy[ok].astype(np.intp)
            r0, r1, c0, c1 = qy.min(), qy.max() + 1, qx.min(), qx.max() + 1
            img = window(ctx.dist, (int(r0), int(r1)), (int(c0), int(c1)))
            flat = np.unique((qy - r0) * (c1 - c0) + (qx - c0))  # the distorted pixels the area covers, once each
            raw = img.ravel()[flat]
        a, b = analysis.grey_statistics(raw), analysis.grey_statistics(reg[inside])
        dvar = 100.0 * (b.variance - a.variance) / a.variance if a.count and a.variance > 0 else None
        label = f"area {k}"
        rows.append([f"{label} (rows {rr[0]}-{rr[1] - 1}, cols {cc[0]}-{cc[1] - 1})", a.mean, b.mean, a.variance,
                     b.variance, a.minimum, b.minimum, a.maximum, b.maximum, a.count, b.count, dvar])
        hists.append((label, raw, reg[inside]))
    page.paragraph("Five square areas of the base grid; 'raw' are the distorted image's own pixels that the "
                   "registration maps into the area (each once, nearest pixel), 'reg.' the registered pixels. "
                   "The registration should leave the grey-level distribution unchanged (the seed: variance within "
                   "2.7 %).")
    page.table(["area", "mean raw", "mean reg.", "var raw", "var reg.", "min raw", "min reg.", "max raw", "max reg.",
                "N raw", "N reg.", "Δvar %"], rows, table_id="grey-table")
    figures.histogram_figure(ctx.plt, ctx.dir / "grey_levels.png", hists)
    page.figure("grey_levels.png", "Grey-level histograms of the areas before (distorted) and after registration.")


def _tiepoint_section(ctx: _Context) -> None:
    page, src = ctx.page, ctx.src
    page.section("tiepoints", "Tie points")
    if src.tiepoints is None or src.tiepoints.sizes.get("point", 0) == 0:
        page.paragraph("The store holds no tie points.", missing=True)
        return
    pts = {k: np.asarray(src.tiepoints[k].values) for k in ("base_x", "base_y", "residual_x", "residual_y", "inlier")}
    background = ctx.level("registered")
    scale = figures.tiepoint_figure(ctx.plt, ctx.dir / "tiepoints.png", background, src.factor, pts, src.shape)
    inl = pts["inlier"].astype(bool)
    res = np.hypot(pts["residual_x"], pts["residual_y"])
    page.figure("tiepoints.png", f"Residual of every tie point against the global polynomial, drawn {scale:.0f} times "
                "longer (cyan: kept by the robust fit, red: rejected).")
    page.table(["tie points", "kept", "RMS residual x (kept)", "RMS residual y (kept)", "RMS |residual| (kept)",
                "max |residual| (kept)"],
               [[int(inl.size), int(inl.sum()), float(np.sqrt(np.mean(pts["residual_x"][inl] ** 2))) if inl.any() else None,
                 float(np.sqrt(np.mean(pts["residual_y"][inl] ** 2))) if inl.any() else None,
                 float(np.sqrt(np.mean(res[inl] ** 2))) if inl.any() else None,
                 float(np.max(res[inl])) if inl.any() else None]])


def _truth_level(t: da.Array, factor: int) -> np.ndarray:
    if factor == 1:
        return np.asarray(t.compute(), dtype=np.float64)
    size = factor * max(1, 512 // factor)
    t = t.rechunk((size, size))
    chunks = tuple(tuple(-(-c // factor) for c in cs) for cs in t.chunks)
    return np.asarray(t.map_blocks(analysis.block_mean, factor, chunks=chunks, dtype=np.float64).compute())


def _truth_section(ctx: _Context, truth) -> None:
    page, src = ctx.page, ctx.src
    page.section("truth", "Against the truth")
    (tx, ty), where = truth
    page.paragraph(f"Truth: {where}.")
    status = ctx.status
    outside = status == int(Status.OUTSIDE)
    ex = np.where(outside, np.nan, ctx.level("dx") - _truth_level(tx, src.factor))
    ey = np.where(outside, np.nan, ctx.level("dy") - _truth_level(ty, src.factor))
    figures.maps_figure(ctx.plt, ctx.dir / "error.png", [("error in x", ex), ("error in y", ey),
                                                          ("|error|", np.hypot(ex, ey))], src.factor,
                        symmetric=[True, True, False], cmap=["RdBu_r", "RdBu_r", "magma"])
    page.figure("error.png", "Displacement minus truth (px)" + (f", overview 1:{src.factor}" if src.factor > 1 else "") + ".")
    sums = status_sums(src, (tx, ty))
    table = analysis.calibration(sums[0], sums[1:3].T, sums[4:6].T, sums[3])
    rows = []
    groups = [(src.legend.get(c, str(c)), [c]) for c in range(sums.shape[1]) if sums[0, c] > 0]
    inside = [c for c in range(sums.shape[1]) if c != int(Status.OUTSIDE)]
    all_inside = analysis.calibration(sums[0, inside].sum(keepdims=True), sums[1:3, inside].sum(axis=1)[None],
                                      sums[4:6, inside].sum(axis=1)[None], sums[3, inside].sum(keepdims=True))[0]
    for name, (c,) in groups:
        t = table[c]
        rows.append([name, int(sums[0, c]), t[0, 0], t[1, 0], t[0, 1], t[1, 1], t[0, 2], t[1, 2]])
    t = all_inside
    rows.append(["all inside the overlap", int(sums[0, inside].sum()), t[0, 0], t[1, 0], t[0, 1], t[1, 1], t[0, 2], t[1, 2]])
    page.paragraph("Sigma calibration over the full-resolution pixels (a Dask reduction): RMSE against the truth over "
                   "the RMS of the matches' sigma, per axis and status; 1 means the sigma are calibrated, above 1 that "
                   "they are optimistic.")
    page.table(["status", "pixels", "RMSE x", "RMSE y", "RMS sigma_x", "RMS sigma_y", "RMSE / RMS sigma x",
                "RMSE / RMS sigma y"], rows, table_id="calibration-table")


# ----------------------------------------------------------------------------- entry point


def report(
    source,
    out: str | os.PathLike,
    *,
    base: str | os.PathLike | None = None,
    distorted: str | os.PathLike | None = None,
    truth=None,
    band: int = 1,
    max_size: int = 1500,
    hsi_size: int = 1024,
    template_length: int | None = None,
    overwrite: bool = False,
) -> str:
    """Write the HTML report of a registration: ``report.html`` and its PNG figures.

    Parameters
    ----------
    source : str, PathLike or xarray.Dataset
        A ``geocoder register`` Zarr store, or the dataset :func:`geocoder.register` returned.
    out : str or PathLike
        The report's directory (local): written whole or not at all, and replaced only if
        ``overwrite`` and geocoder wrote it.
    base, distorted : str or PathLike, optional
        The input images; default the paths the store's summary records. The base is needed
        for the HSI check, the distorted image for the polynomial-only composite and the
        grey-level statistics; the page says so when either is missing.
    truth : str, PathLike or (array, array), optional
        The true displacement: a ``(dx, dy)`` pair on the base grid, a Zarr store with
        ``dx`` and ``dy``, or the store of ``geocoder simulate`` whose ortho is the base.
        Adds the error map and the sigma calibration.
    band : int
        1-based band of the base and registered images shown.
    max_size : int
        Largest side (pixels) of the maps: the finest overview level at most this large.
    hsi_size : int
        Side of the full-resolution window of the HSI check (the whole scene if smaller).
    template_length : int, optional
        Length (px) along the scan line over which neighbouring matches share pixels (their
        noise is correlated): the along-track noise floor counts ``n / template_length``
        independent matches per line. Default: the dense matcher's template (51 px).
    overwrite : bool
        Replace an earlier report there.

    Returns
    -------
    str
        The report's directory.
    """
    from . import require_matplotlib

    plt = require_matplotlib()
    store = None if not isinstance(source, (str, os.PathLike)) else os.fspath(source)
    inputs = [store, base, distorted] + ([truth] if isinstance(truth, (str, os.PathLike)) else [])
    final = check_output(out, inputs=[i for i in inputs if i is not None], overwrite=overwrite, option="--out")
    if storage.is_url(final):
        raise InputError(final, "a report is written to a local directory")
    if not os.path.isdir(os.path.dirname(final)):
        raise InputError(final, "the report's parent directory does not exist")
    if band < 1:
        raise ValueError(f"band must be >= 1, got {band}")
    src = open_source(source, max_size=max_size)
    truth_data = read_truth(truth, src) if truth is not None else None
    tmp = storage.temporary_sibling(final)
    os.makedirs(tmp)
    try:
        with warnings.catch_warnings():  # raw scanner images have no georeference, and need none here
            warnings.filterwarnings("ignore", message=".*no geotransform.*")
            page = Page(f"Registration report: {os.path.basename(str(store or 'dataset').rstrip('/'))}")
            ctx = _Context(plt, Path(tmp), src, page, band, base, distorted, hsi_size, template_length)
            _summary_section(ctx)
            _hsi_section(ctx)
            _disparity_section(ctx)
            _along_track_section(ctx, truth_data)
            _grey_section(ctx)
            _tiepoint_section(ctx)
            if truth_data is not None:
                _truth_section(ctx, truth_data)
        (Path(tmp) / PAGE).write_text(page.render(), encoding="utf-8")
        write_marker(tmp, PRODUCT)
        commit_output(tmp, final, overwrite=overwrite)
    except BaseException:
        storage.remove(tmp)
        raise
    return final
