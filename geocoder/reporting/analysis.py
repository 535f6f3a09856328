"""Pure arithmetic of the registration report: numpy in, numpy out, no files, no plotting.

* :func:`hsi` and :func:`hsi_composite`: the hue-saturation-intensity check of seed 003
  sec. 8 (RGB = base, registered, registered);
* :func:`line_spectrum`: the along-track analysis of sec. 9 (the per-scan-line mean
  displacement after the polynomial, its power spectrum and the frequency where it meets
  the noise floor of the matches);
* :func:`grey_statistics`: the grey-level statistics of sec. 8 (Table 3);
* :func:`calibration`: RMSE against truth over RMS of the matches' sigma, per status;
* :func:`polynomial_grid` and :func:`block_mean`: a polynomial displacement and a block
  average on a (level) grid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..kernels.polynomial import PolyMap, exponents

__all__ = [
    "AlongTrack",
    "GreyStatistics",
    "block_mean",
    "calibration",
    "grey_statistics",
    "hsi",
    "hsi_composite",
    "line_spectrum",
    "polynomial_grid",
    "shift_image",
    "stretch",
]


def stretch(image: np.ndarray, *, percentiles: tuple[float, float] = (1.0, 99.0)) -> np.ndarray:
    """Linear stretch of an image to [0, 1] between two percentiles of its finite values.

    Parameters
    ----------
    image : numpy.ndarray
        Any shape; NaN is nodata and stays NaN.
    percentiles : tuple of float
        Low and high percentile mapped to 0 and 1 (values beyond are clipped).

    Returns
    -------
    numpy.ndarray
        float64, same shape, in [0, 1] or NaN.
    """
    a = np.asarray(image, dtype=np.float64)
    finite = np.isfinite(a)
    if not finite.any():
        return np.full(a.shape, np.nan)
    lo, hi = np.percentile(a[finite], percentiles)
    out = np.clip((a - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    return np.where(finite, out, np.nan)


def hsi(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hue, saturation and intensity of RGB values in [0, 1] (the geometric HSI model).

    Parameters
    ----------
    rgb : numpy.ndarray
        Shape ``(3, ...)``: red, green, blue.

    Returns
    -------
    hue : numpy.ndarray
        Degrees in [0, 360): 0 red, 120 green, 240 blue; 0 where the colour is grey
        (hue undefined).
    saturation : numpy.ndarray
        ``1 - min(R, G, B) / I`` in [0, 1]; 0 for black.
    intensity : numpy.ndarray
        ``(R + G + B) / 3``.

    Notes
    -----
    ``theta = arccos(((R - G) + (R - B)) / 2 / sqrt((R - G)^2 + (R - B)(G - B)))`` and the
    hue is ``theta`` if ``B <= G``, else ``360 - theta``. NaN in any channel gives NaN.
    """
    c = np.asarray(rgb, dtype=np.float64)
    if c.shape[0] != 3:
        raise ValueError(f"rgb must have 3 channels on its first axis, got shape {c.shape}")
    r, g, b = c
    intensity = (r + g + b) / 3.0
    low = np.minimum(np.minimum(r, g), b)
    with np.errstate(invalid="ignore", divide="ignore"):
        saturation = np.where(intensity > 0, 1.0 - low / intensity, 0.0)
        num = 0.5 * ((r - g) + (r - b))
        den = np.sqrt((r - g) ** 2 + (r - b) * (g - b))
        theta = np.degrees(np.arccos(np.clip(num / np.where(den > 0, den, 1.0), -1.0, 1.0)))
    hue = np.where(den > 0, np.where(b > g, 360.0 - theta, theta), 0.0)
    hue = np.where(hue >= 360.0, hue - 360.0, hue)
    nan = ~np.all(np.isfinite(c), axis=0)
    return (np.where(nan, np.nan, hue), np.where(nan, np.nan, np.clip(saturation, 0.0, 1.0)),
            np.where(nan, np.nan, intensity))


def hsi_composite(base: np.ndarray, registered: np.ndarray, *,
                  percentiles: tuple[float, float] = (1.0, 99.0)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """HSI of the composite RGB = (base, registered, registered) (seed 003 sec. 8).

    Each image is stretched to [0, 1] between its own percentiles first, so a gain or an
    offset between the two images does not colour the composite; where they agree the
    composite is grey (saturation 0), a misregistered edge shows as a saturated red (base
    brighter) or cyan (registered brighter) fringe.

    Parameters
    ----------
    base, registered : numpy.ndarray
        Images of the same shape on the base grid; NaN is nodata.
    percentiles : tuple of float
        Stretch of each image (:func:`stretch`).

    Returns
    -------
    hue, saturation, intensity : numpy.ndarray
        As :func:`hsi`; NaN where either image is nodata.
    """
    base = np.asarray(base)
    registered = np.asarray(registered)
    if base.shape != registered.shape:
        raise ValueError(f"base and registered differ in shape: {base.shape} != {registered.shape}")
    valid = np.isfinite(base) & np.isfinite(registered)
    b = stretch(np.where(valid, base, np.nan), percentiles=percentiles)
    r = stretch(np.where(valid, registered, np.nan), percentiles=percentiles)
    return hsi(np.stack([b, r, r]))


def shift_image(image: np.ndarray, rows: int = 1, cols: int = 1) -> np.ndarray:
    """The image moved ``rows`` down and ``cols`` right (the seed's Figure 5 control); NaN enters.

    Parameters
    ----------
    image : numpy.ndarray
        2-D image.
    rows, cols : int
        Shift in whole pixels (non-negative: down and right).

    Returns
    -------
    numpy.ndarray
        float64, ``out[r, c] = image[r - rows, c - cols]``, NaN where that is outside.
    """
    a = np.asarray(image, dtype=np.float64)
    if rows < 0 or cols < 0:
        raise ValueError("shift_image moves down and right: rows and cols must be >= 0")
    out = np.full(a.shape, np.nan)
    h, w = a.shape
    if rows < h and cols < w:
        out[rows:, cols:] = a[: h - rows, : w - cols]
    return out


def polynomial_grid(mapping: PolyMap, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Displacement ``mapping(x, y) - (x, y)`` on the grid ``y x x`` (outer product), float64.

    Parameters
    ----------
    mapping : PolyMap
        Base -> distorted pixel polynomial (the store's ``mapping`` attribute).
    x, y : numpy.ndarray
        1-D column and row coordinates (pixel centres, full-resolution pixels).

    Returns
    -------
    dx, dy : numpy.ndarray
        Shape ``(len(y), len(x))``.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    u = (x - mapping.centre[0]) / mapping.scale
    v = (y - mapping.centre[1]) / mapping.scale
    out = np.zeros((2, y.size, x.size))
    for k, (i, j) in enumerate(exponents(mapping.order)):  # separable monomials: order+1 .. 10 passes
        term = (v**j)[:, None] * (u**i)[None, :]
        out[0] += mapping.coef[k, 0] * term
        out[1] += mapping.coef[k, 1] * term
    return out[0] - x[None, :], out[1] - y[:, None]


def block_mean(image: np.ndarray, factor: int) -> np.ndarray:
    """Mean of the finite pixels of every ``factor x factor`` block (the overview levels' rule).

    Parameters
    ----------
    image : numpy.ndarray
        2-D image; NaN is nodata. Sides that do not divide are padded with nodata.
    factor : int
        Block side.

    Returns
    -------
    numpy.ndarray
        Shape ``(ceil(h / factor), ceil(w / factor))``, NaN where a block has no finite pixel.
    """
    a = np.asarray(image, dtype=np.float64)
    if factor == 1:
        return a.copy()
    h, w = a.shape
    ph, pw = -h % factor, -w % factor
    a = np.pad(a, ((0, ph), (0, pw)), constant_values=np.nan)
    blocks = a.reshape(a.shape[0] // factor, factor, a.shape[1] // factor, factor)
    valid = np.isfinite(blocks)
    n = valid.sum(axis=(1, 3))
    total = np.where(valid, blocks, 0.0).sum(axis=(1, 3))
    out = np.full(total.shape, np.nan)
    np.divide(total, n, out=out, where=n > 0)
    return out


@dataclass(frozen=True)
class AlongTrack:
    """The along-track analysis of one displacement component (seed 003 sec. 9).

    Attributes
    ----------
    mean : numpy.ndarray
        Per scan line (row): mean displacement of the matches after the polynomial (px);
        NaN for a line without matches.
    noise_variance : numpy.ndarray
        Per line: variance of that mean from the matches' sigma (``mean sigma^2 / n``).
    frequency : numpy.ndarray
        Line frequencies ``k / N`` (cycles per line), ``k = 1 .. N // 2``.
    power : numpy.ndarray
        Periodogram of the gap-filled, detrended, Hann-windowed line means at ``frequency``
        (px^2; white noise of variance ``v`` per line has expectation ``v``).
    smoothed : numpy.ndarray
        ``power`` averaged over ``smooth`` neighbouring frequencies.
    floor : float
        Noise floor: the mean of ``noise_variance`` over the lines with matches (px^2).
    tail : float
        Median of ``power`` over the highest quarter of frequencies (an empirical floor).
    peak_frequency : float
        Frequency of the largest smoothed power (cycles per line).
    noise_frequency : float
        Lowest frequency above the peak at which the smoothed spectrum falls to the floor:
        above it the energy is noise. 0.5 (Nyquist) if it never does, NaN when the whole
        spectrum is below the floor (no signal above noise).
    coverage : float
        Fraction of lines with at least one match.
    """

    mean: np.ndarray
    noise_variance: np.ndarray
    frequency: np.ndarray
    power: np.ndarray
    smoothed: np.ndarray
    floor: float
    tail: float
    peak_frequency: float
    noise_frequency: float
    coverage: float

    @property
    def sampling_lines(self) -> int | None:
        """Sampling interval (lines) an INS needs to follow the signal: ``floor(1 / (2 f_noise))``.

        None when there is no signal above noise.
        """
        if not np.isfinite(self.noise_frequency) or self.noise_frequency <= 0:
            return None
        return max(1, int(np.floor(1.0 / (2.0 * self.noise_frequency))))


def _fill_gaps(series: np.ndarray) -> np.ndarray:
    """NaN entries linearly interpolated from their finite neighbours (clamped at the ends)."""
    idx = np.arange(series.size, dtype=np.float64)
    ok = np.isfinite(series)
    return np.interp(idx, idx[ok], series[ok])


def line_spectrum(mean: np.ndarray, noise_variance: np.ndarray, *, smooth: int = 5) -> AlongTrack:
    """Power spectrum of the per-line mean displacement and where it meets the matches' noise.

    Parameters
    ----------
    mean : numpy.ndarray
        1-D, per scan line: the mean displacement after the polynomial (NaN: no matches).
    noise_variance : numpy.ndarray
        1-D, per line: the variance of ``mean`` from the matching noise (e.g. the mean
        ``sigma^2`` of the line's matches over their number); NaN where ``mean`` is.
    smooth : int
        Number of neighbouring frequencies averaged before the spectrum is compared with the
        floor (odd; 1 compares the raw periodogram).

    Returns
    -------
    AlongTrack
        The spectrum, the floor and the noise frequency.

    Notes
    -----
    Lines without matches are filled by linear interpolation, a straight line is removed,
    and a Hann window ``w`` tapers the series; the periodogram is ``|FFT(w x)|^2 / sum(w^2)``
    so that white noise of variance ``v`` has an expected power ``v`` at every frequency:
    the floor is then directly the mean noise variance of a line mean. The energy above the
    noise frequency is indistinguishable from matching noise; an instrument recording the
    attitude must sample at least twice per period of the noise frequency (Nyquist) to
    follow what is below it (seed 003 sec. 9).
    """
    m = np.asarray(mean, dtype=np.float64).ravel()
    var = np.asarray(noise_variance, dtype=np.float64).ravel()
    if m.shape != var.shape:
        raise ValueError(f"mean and noise_variance differ in length: {m.size} != {var.size}")
    ok = np.isfinite(m)
    n = m.size
    empty = np.zeros(0)
    if ok.sum() < 8:
        return AlongTrack(m, var, empty, empty, empty, float("nan"), float("nan"), float("nan"), float("nan"),
                          float(ok.mean()) if n else 0.0)
    series = _fill_gaps(m)
    lines = np.arange(n, dtype=np.float64)
    series = series - np.polyval(np.polyfit(lines, series, 1), lines)
    window = np.hanning(n) if n > 2 else np.ones(n)
    spec = np.fft.rfft(series * window)
    power = (np.abs(spec) ** 2 / np.sum(window**2))[1:]
    frequency = np.fft.rfftfreq(n)[1:]
    smooth = max(1, int(smooth) | 1)
    smoothed = ndimage.uniform_filter1d(power, size=smooth, mode="nearest") if smooth > 1 else power.copy()
    good = ok & np.isfinite(var)
    floor = float(np.mean(var[good])) if good.any() else float("nan")
    tail = float(np.median(power[-max(1, power.size // 4):]))
    peak = int(np.argmax(smoothed))
    if not np.isfinite(floor) or not np.any(smoothed > floor):
        noise_frequency = float("nan")
    else:
        below = np.nonzero(smoothed[peak:] <= floor)[0]
        noise_frequency = float(frequency[peak + below[0]]) if below.size else 0.5
    return AlongTrack(m, var, frequency, power, smoothed, floor, tail, float(frequency[peak]), noise_frequency,
                      float(ok.mean()))


@dataclass(frozen=True)
class GreyStatistics:
    """Grey-level statistics of an image area (seed 003 Table 3).

    Attributes
    ----------
    mean, variance, minimum, maximum : float
        Of the finite values (population variance).
    count : int
        Number of finite values.
    """

    mean: float
    variance: float
    minimum: float
    maximum: float
    count: int


def grey_statistics(values: np.ndarray) -> GreyStatistics:
    """Mean, variance, extremes and number of the finite grey values of an area.

    Parameters
    ----------
    values : numpy.ndarray
        Grey values, any shape; NaN is nodata.

    Returns
    -------
    GreyStatistics
        All NaN (count 0) when no value is finite.
    """
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return GreyStatistics(float("nan"), float("nan"), float("nan"), float("nan"), 0)
    return GreyStatistics(float(v.mean()), float(v.var()), float(v.min()), float(v.max()), int(v.size))


def calibration(count: np.ndarray, error2: np.ndarray, sigma2: np.ndarray, sigma_count: np.ndarray) -> np.ndarray:
    """RMSE against truth, RMS sigma and their ratio per group and axis.

    Parameters
    ----------
    count : numpy.ndarray
        Shape ``(g,)``: pixels per group (e.g. per status) with a finite error.
    error2 : numpy.ndarray
        Shape ``(g, 2)``: sum of squared errors in x and y.
    sigma2 : numpy.ndarray
        Shape ``(g, 2)``: sum of squared sigma in x and y over the pixels that have one.
    sigma_count : numpy.ndarray
        Shape ``(g,)``: pixels per group with a finite sigma (and error).

    Returns
    -------
    numpy.ndarray
        Shape ``(g, 2, 3)``: per group and axis, ``RMSE``, ``RMS sigma`` and
        ``RMSE / RMS sigma`` (1 for a calibrated sigma; NaN where undefined).
    """
    count = np.asarray(count, dtype=np.float64)
    sigma_count = np.asarray(sigma_count, dtype=np.float64)
    out = np.full((count.size, 2, 3), np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        rmse = np.sqrt(np.asarray(error2, dtype=np.float64) / count[:, None])
        rms_sigma = np.sqrt(np.asarray(sigma2, dtype=np.float64) / sigma_count[:, None])
        out[..., 0] = np.where(count[:, None] > 0, rmse, np.nan)
        out[..., 1] = np.where(sigma_count[:, None] > 0, rms_sigma, np.nan)
        out[..., 2] = out[..., 0] / out[..., 1]
    return out
