"""The registration report (issue 15 part 1): pure kernels against hand values, then the page
of a real register run on a simulated pair with known truth.

Kernels: the HSI of known colours, the along-track spectrum of a known per-line sinusoid in
white noise, grey statistics, the calibration ratio, the polynomial on a grid. Pipeline: a
real S2 crop warped with scan-line turbulence is registered on the test cluster; the report
of the store (with the truth) has every section and figure, the figures show something, the
HSI check ranks the registration above the polynomial and the 1-pixel shift, the calibration
table is there; the CLI writes it too and refuses to write over a user's directory.
"""

from __future__ import annotations

import re
import sys

import numpy as np
import pytest
from numpy.testing import assert_allclose

from geocoder.errors import EnvironmentFailure, OutputError
from geocoder.kernels.polynomial import PolyMap
from geocoder.reporting import analysis

FIGURES = ["hsi.png", "disparity.png", "status.png", "sigma.png", "along_track.png", "grey_levels.png",
           "tiepoints.png"]
SECTIONS = ["summary", "coarse", "hsi", "disparity", "status", "along-track", "grey", "tiepoints"]


# ----------------------------------------------------------------------------- kernels


@pytest.mark.parametrize("rgb, hue, sat, inten", [
    ((1.0, 0.0, 0.0), 0.0, 1.0, 1 / 3),  # pure red
    ((0.0, 1.0, 0.0), 120.0, 1.0, 1 / 3),  # pure green
    ((0.0, 0.0, 1.0), 240.0, 1.0, 1 / 3),  # pure blue
    ((1.0, 1.0, 0.0), 60.0, 1.0, 2 / 3),  # yellow
    ((0.0, 1.0, 1.0), 180.0, 1.0, 2 / 3),  # cyan: registered brighter than base
    ((0.5, 0.5, 0.5), 0.0, 0.0, 0.5),  # grey: base and registered agree
    ((0.0, 0.0, 0.0), 0.0, 0.0, 0.0),  # black
    ((0.8, 0.4, 0.4), 0.0, 1 - 0.4 / (1.6 / 3), 1.6 / 3),  # base brighter: a red tint
])
def test_hsi_of_known_colours(rgb, hue, sat, inten):
    h, s, i = analysis.hsi(np.array(rgb, dtype=float).reshape(3, 1))
    assert_allclose([h[0], s[0], i[0]], [hue, sat, inten], atol=1e-9)


def test_hsi_nan_and_shape():
    rgb = np.random.default_rng(0).uniform(size=(3, 4, 5))
    rgb[1, 2, 3] = np.nan
    h, s, i = analysis.hsi(rgb)
    assert h.shape == s.shape == i.shape == (4, 5)
    assert np.isnan(s[2, 3]) and np.isfinite(np.delete(s.ravel(), 2 * 5 + 3)).all()
    assert ((h >= 0) & (h < 360))[np.isfinite(h)].all()
    with pytest.raises(ValueError):
        analysis.hsi(np.zeros((2, 3)))


def test_hsi_composite_is_grey_where_the_images_agree():
    rng = np.random.default_rng(1)
    img = rng.uniform(0, 1000, size=(64, 64))
    _, s, _ = analysis.hsi_composite(img, 0.8 * img + 30)  # a gain and an offset do not colour it
    assert_allclose(s[np.isfinite(s)], 0.0, atol=0.02)
    _, shifted, _ = analysis.hsi_composite(img, analysis.shift_image(img, 1, 1))
    assert np.nanmean(shifted) > 0.2
    assert np.isnan(shifted[0]).all() and np.isnan(shifted[:, 0]).all()


def test_line_spectrum_finds_a_known_period_and_the_noise_above_it():
    n, period, sigma = 2048, 40.0, 0.05
    rng = np.random.default_rng(2)
    lines = np.arange(n)
    mean = 0.5 * np.sin(2 * np.pi * lines / period) + rng.normal(0, sigma, n)
    mean[300:310] = np.nan  # lines without matches
    var = np.full(n, sigma**2)
    at = analysis.line_spectrum(mean, var)
    assert_allclose(at.peak_frequency, 1 / period, atol=1.5 / n)
    assert at.floor == pytest.approx(sigma**2)
    assert at.tail == pytest.approx(sigma**2, rel=0.3)  # the white part of the spectrum is at the floor
    assert 1 / period < at.noise_frequency < 1.5 / period  # the sinusoid's peak is all the signal
    assert at.sampling_lines == int(np.floor(1 / (2 * at.noise_frequency)))
    assert at.coverage == pytest.approx(1 - 10 / n)
    # the periodogram is normalised so that white noise of variance v has power v
    white = analysis.line_spectrum(rng.normal(0, 0.1, n), np.full(n, 0.01))
    assert np.mean(white.power) == pytest.approx(0.01, rel=0.1)


def test_line_spectrum_of_a_line_signal_above_noise_everywhere_and_of_too_few_lines():
    n = 512
    rng = np.random.default_rng(3)
    mean = rng.normal(0, 1.0, n)  # strong line-to-line signal, tiny matching noise
    at = analysis.line_spectrum(mean, np.full(n, 1e-6))
    assert at.noise_frequency == 0.5 and at.sampling_lines == 1
    quiet = analysis.line_spectrum(np.zeros(n), np.full(n, 1.0))  # nothing above the floor
    assert np.isnan(quiet.noise_frequency) and quiet.sampling_lines is None
    few = analysis.line_spectrum(np.array([1.0, np.nan, 2.0]), np.ones(3))
    assert few.frequency.size == 0 and np.isnan(few.noise_frequency)


def test_grey_statistics_and_calibration():
    v = np.array([[1.0, 2.0, np.nan], [3.0, 4.0, 10.0]])
    g = analysis.grey_statistics(v)
    ref = np.array([1.0, 2.0, 3.0, 4.0, 10.0])
    assert (g.mean, g.variance, g.minimum, g.maximum, g.count) == pytest.approx((ref.mean(), ref.var(), 1, 10, 5))
    assert analysis.grey_statistics(np.full(3, np.nan)).count == 0
    # two groups: errors of RMS (0.2, 0.4) against sigma of RMS (0.1, 0.4); an empty group
    table = analysis.calibration(np.array([4, 0]), np.array([[4 * 0.04, 4 * 0.16], [0, 0]]),
                                 np.array([[2 * 0.01, 2 * 0.16], [0, 0]]), np.array([2, 0]))
    assert_allclose(table[0], [[0.2, 0.1, 2.0], [0.4, 0.4, 1.0]])
    assert np.isnan(table[1]).all()


def test_polynomial_grid_and_block_mean():
    coef = np.array([[3.0, -2.0], [1.01, 0.02], [-0.01, 0.98], [0.3, -0.2], [0.1, 0.05], [-0.2, 0.4]])
    mapping = PolyMap(coef, 2, (50.0, 40.0), 60.0)
    x, y = np.arange(0, 100, 7.0), np.arange(0, 80, 3.0)
    dx, dy = analysis.polynomial_grid(mapping, x, y)
    xx, yy = np.meshgrid(x, y)
    px, py = mapping(xx, yy)
    assert_allclose(dx, px - xx, atol=1e-9)
    assert_allclose(dy, py - yy, atol=1e-9)
    img = np.arange(35.0).reshape(5, 7)
    img[0, 0] = np.nan
    m = analysis.block_mean(img, 2)
    assert m.shape == (3, 4)
    assert m[0, 0] == pytest.approx(np.mean([1, 7, 8]))  # the NaN does not count
    assert m[2, 3] == img[4, 6]  # a padded corner: its one valid pixel


def test_missing_matplotlib_names_the_extra(monkeypatch):
    from geocoder.reporting import require_matplotlib

    monkeypatch.setitem(sys.modules, "matplotlib", None)
    with pytest.raises(EnvironmentFailure, match=r"geocoder\[report\]"):
        require_matplotlib()


# ----------------------------------------------------------------------------- a real run


@pytest.fixture(scope="module")
def registered(s2_turbulence):
    """A real S2 crop with scan-line turbulence of known truth, registered into a store, and its report
    against the truth (the session's, shared with test_report_browser.py)."""
    return s2_turbulence


def _png_ok(path) -> bool:
    import matplotlib.image as mpimg

    img = mpimg.imread(path)
    return path.stat().st_size > 5000 and float(np.std(img[..., :3])) > 0.02


def _table(page: str, table_id: str) -> list[list[str]]:
    body = page[page.index(f'id="{table_id}"'):]
    body = body[: body.index("</table>")]
    return [re.findall(r"<td[^>]*>([^<]*)</td>", row) for row in body.split("<tr>")[2:]]


def test_report_of_a_registration_against_truth(registered, client):
    d, out, files, where = registered  # where = report(out, d / "report", truth=(files.pair.dx, files.pair.dy))
    page = (d / "report" / "report.html").read_text()
    for anchor in SECTIONS + ["truth"]:
        assert f'id="{anchor}"' in page, anchor
    for name in FIGURES + ["error.png"]:
        assert f'src="{name}"' in page and _png_ok(d / "report" / name), name
    assert "http" not in page.replace("http-equiv", "")  # nothing fetched from the network
    assert 'class="missing"' not in page  # base and distorted found from the summary
    # HSI: the registration is closer to the base than the polynomial alone and than the 1-px shift
    sat = {row[0]: float(row[1]) for row in _table(page, "hsi-table")}
    assert sat["registered"] < sat["polynomial only"] and sat["registered"] < sat["registered, shifted 1 px down and right"]
    # along-track: both components analysed, an INS interval in lines
    rows = _table(page, "along-track-table")
    assert [r[0] for r in rows] == ["dx", "dy"] and all(r[-1].isdigit() for r in rows)
    # grey statistics of five areas: the registration keeps the mean within 1 %; the bilinear resampling
    # smooths (the variance drops, most on a flat, noisy field: -23 % here), it never adds variance
    grey = _table(page, "grey-table")
    assert len(grey) == 5
    for r in grey:
        assert float(r[2]) == pytest.approx(float(r[1]), rel=0.01) and -30 < float(r[11]) < 2
    # the calibration table: matched pixels sub-pixel, with sigma of the right order
    cal = {r[0]: r for r in _table(page, "calibration-table")}
    assert "matched" in cal and "all inside the overlap" in cal
    rmse = float(cal["matched"][2]), float(cal["matched"][3])
    ratio = float(cal["matched"][6]), float(cal["matched"][7])
    assert max(rmse) < 0.3 and all(0.3 < q < 5 for q in ratio)
    assert where == str(d / "report")


def test_report_cli_with_truth_store_missing_base_and_the_output_guard(registered, client, tmp_path):
    import xarray as xr
    from cli_batch import run_batch

    _, out, files, _ = registered
    d = tmp_path
    xr.Dataset({"dx": (("y", "x"), files.pair.dx), "dy": (("y", "x"), files.pair.dy)}).to_zarr(
        d / "truth.zarr", mode="w", zarr_format=3, consolidated=False)
    user = d / "mine"
    user.mkdir()
    (user / "notes.txt").write_text("keep me")
    # the three command lines in one process, one after the other (see cli_batch)
    runs = run_batch({
        "report": ["report", out, "--out", d / "cli", "--truth", d / "truth.zarr", "--base", d / "moved.tif", "--max-size", 128],
        # an earlier report is replaced only with --overwrite; a user's directory never
        "again": ["report", out, "--out", d / "cli"],
        "user's directory": ["report", out, "--out", user, "--overwrite"],
    }, d)
    r, _ = runs["report"]
    assert r.returncode == 0, r.stderr
    page = (d / "cli" / "report.html").read_text()
    assert "calibration-table" in page and "overview level 1:2" in page  # 256 px shown from level 1
    assert 'class="missing">The base image is missing' in page and not (d / "cli" / "hsi.png").exists()
    r, _ = runs["again"]
    assert r.returncode == 2 and "--overwrite" in r.stderr
    r, _ = runs["user's directory"]
    assert r.returncode == 2 and "did not write" in r.stderr
    assert (user / "notes.txt").read_text() == "keep me" and sorted(p.name for p in user.iterdir()) == ["notes.txt"]
    with pytest.raises(OutputError):
        from geocoder import report

        report(out, out / "inside")  # inside its own input
