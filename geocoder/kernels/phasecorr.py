"""Phase correlation and Fourier-Mellin similarity estimation.

Used for the automatic coarse alignment of two (downsampled, <= ~1024 px)
images without any prior overlap estimate.

Conventions
-----------
* Pixel coordinates follow ``CONVENTIONS.md``: ``x`` = column, ``y`` = row,
  the centre of pixel ``[r, c]`` is at ``(x=c, y=r)``; NaN is nodata.
* :func:`phase_correlation` returns the displacement ``(dx, dy) = p_b - p_a``
  of the same feature, i.e. ``b(x + dx, y + dy) ~= a(x, y)``.
* :func:`estimate_similarity` returns a 2x3 matrix ``A`` with
  ``p_b = A[:, :2] @ p_a + A[:, 2]`` (pixel coordinates about the arrays'
  origin, pixel ``[0, 0]`` at ``(0, 0)``) and

  .. code-block:: text

      A[:, :2] = scale * [[ cos(angle), sin(angle)],
                          [-sin(angle), cos(angle)]]

  so a positive ``angle`` is a counter-clockwise rotation *as the image is
  displayed* (row 0 at the top, y pointing down): a feature to the right of
  the origin, ``(1, 0)``, moves to ``(s cos, -s sin)``, i.e. up.  This is the
  same sign as ``scipy.ndimage.rotate``, scikit-image's ``rotate`` and
  OpenCV's ``getRotationMatrix2D``: ``b = scipy.ndimage.rotate(a, 30)``
  gives ``angle = +30`` degrees.  ``angle`` is in radians, in ``(-pi, pi]``.

Pre-processing: NaN pixels are replaced by the (window-weighted) finite mean,
the mean is removed and the image is multiplied by an apodisation window
(a separable Hann window for phase correlation, a radial Tukey window for the
rotation-invariant Fourier-Mellin spectra) and, when there is nodata, by a
raised-cosine taper that falls to zero at the nodata boundary (so NaN
borders and NaN corners of rotated scenes do not create spurious edges).

The cross-power spectrum is normalised (whitened) and weighted by a Gaussian
low-pass ``exp(-|f|^2 / (2 sigma^2))`` with ``sigma = 1/8`` cycle/pixel, so
the correlation peak is a smooth ~Gaussian blob (sigma ~1.3 px) whose
position is located to sub-pixel precision by a 3-point Gaussian (quadratic
in the logarithm) fit along each axis of the 3x3 neighbourhood of the integer
maximum, with a parabolic fit as fallback.  The correlation surface is
normalised so that two identical images give a peak of 1; unrelated images
give a few hundredths.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from geocoder.kernels.resample import sample

__all__ = ["Shift", "Similarity", "phase_correlation", "estimate_similarity"]

# Gaussian low-pass of the whitened cross-power spectrum, cycles / pixel.
_LOWPASS_SIGMA = 1.0 / 8.0

# Tapered fraction of the radius of the radial (rotation-invariant) window
# applied before the Fourier-Mellin spectra.
_RADIAL_TAPER = 0.5

# Fourier-Mellin re-estimations of the residual rotation/scale.
_REFINE_ITERATIONS = 2
# A refinement is kept if its translation peak is at least this fraction of
# the previous one (the peak height itself varies by a few percent).
_REFINE_TOLERANCE = 0.95

# Rotation/scale candidates (log-polar correlation maxima) verified by the
# translation correlation, each with both 180-degree alternatives.
_CANDIDATES = 3


@dataclass(frozen=True)
class Shift:
    """Translation between two images.

    Attributes
    ----------
    dx, dy : float
        Displacement ``p_b - p_a`` in pixels (``b(x + dx, y + dy) ~= a(x, y)``);
        NaN when the images have no usable texture.
    peak : float
        Height of the normalised correlation peak in ``[0, 1]`` (1 for
        identical images, a few hundredths for unrelated ones).
    """

    dx: float
    dy: float
    peak: float


@dataclass(frozen=True)
class Similarity:
    """Similarity transform from image ``a`` to image ``b``.

    Attributes
    ----------
    matrix : numpy.ndarray
        2x3 float64 matrix mapping an ``a`` pixel ``(x, y)`` to the ``b``
        pixel ``A[:, :2] @ (x, y) + A[:, 2]``; NaN when no estimate exists.
    scale : float
        Scale factor (``b`` pixels per ``a`` pixel).
    angle : float
        Rotation in radians, counter-clockwise positive as displayed
        (see the module docstring for the exact matrix).
    peak : float
        Normalised peak height of the final translation correlation.
    """

    matrix: np.ndarray
    scale: float
    angle: float
    peak: float


# --------------------------------------------------------------------------
# pre-processing
# --------------------------------------------------------------------------


def _hann_separable(shape: tuple[int, int]) -> np.ndarray:
    """Separable Hann window without zero end samples."""
    wy = np.hanning(shape[0] + 2)[1:-1]
    wx = np.hanning(shape[1] + 2)[1:-1]
    return np.outer(wy, wx)


def _tukey_radial(shape: tuple[int, int], alpha: float = _RADIAL_TAPER) -> np.ndarray:
    """Radial Tukey window: 1 up to ``1 - alpha`` of the inscribed radius, then a cosine to 0."""
    h, w = shape
    yy = (np.arange(h) - (h - 1) / 2.0)[:, None]
    xx = (np.arange(w) - (w - 1) / 2.0)[None, :]
    rho = np.hypot(yy, xx) / (min(h, w) / 2.0)
    t = np.clip((rho - (1.0 - alpha)) / alpha, 0.0, 1.0)
    return 0.5 + 0.5 * np.cos(np.pi * t)


def _nodata_taper(valid: np.ndarray) -> np.ndarray:
    """Taper from 0 at the nodata boundary to 1 about ``width`` pixels inside.

    The fraction ``f`` of valid pixels in a ``(2 width + 1)``-wide box is 1/2
    on a straight nodata edge and 1 at ``width`` pixels from it, so
    ``2 f - 1`` is a cheap ramp of the distance to the edge; it is shaped as a
    raised cosine.
    """
    if valid.all():
        return np.ones(valid.shape)
    width = int(max(4, min(valid.shape) // 16))
    frac = ndimage.uniform_filter(valid.astype(np.float64), size=2 * width + 1, mode="nearest")
    t = np.clip(2.0 * frac - 1.0, 0.0, 1.0)
    return np.where(valid, 0.5 - 0.5 * np.cos(np.pi * t), 0.0)


def _apodise(image: np.ndarray, window: np.ndarray) -> np.ndarray | None:
    """Mean-removed, NaN-filled, windowed copy of ``image`` (None if textureless)."""
    image = np.asarray(image, dtype=np.float64)
    valid = np.isfinite(image)
    if not valid.any():
        return None
    weight = window * _nodata_taper(valid)
    total = weight.sum()
    if total <= 0.0:
        return None
    values = np.where(valid, image, 0.0)
    mean = float(np.sum(weight * values) / total)
    out = np.where(valid, image - mean, 0.0) * weight
    if not np.any(out):
        return None
    return out


# --------------------------------------------------------------------------
# correlation surface and peak
# --------------------------------------------------------------------------


def _correlation_surface(pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    """Normalised, low-pass weighted phase-correlation surface (peak at ``p_b - p_a``)."""
    shape = pa.shape
    fa = np.fft.rfft2(pa)
    fb = np.fft.rfft2(pb)
    cross = fb * np.conj(fa)
    mag = np.abs(cross)
    keep = mag > 1e-12 * mag.max()
    keep[0, 0] = False  # the mean is removed; its phase is meaningless
    fy = np.fft.fftfreq(shape[0])[:, None]
    fx = np.fft.rfftfreq(shape[1])[None, :]
    gauss = np.where(keep, np.exp(-(fy**2 + fx**2) / (2.0 * _LOWPASS_SIGMA**2)), 0.0)
    # Sum over the full (two-sided) spectrum: the half spectrum holds the
    # columns 1 .. ceil(W/2) - 1 once for two.
    multiplicity = np.full(fx.shape, 2.0)
    multiplicity[0, 0] = 1.0
    if shape[1] % 2 == 0:
        multiplicity[0, -1] = 1.0
    norm = float(np.sum(gauss * multiplicity))
    if norm <= 0.0:
        return np.zeros(shape)
    spec = cross / np.where(keep, mag, 1.0) * gauss
    return np.fft.irfft2(spec, s=shape) * (pa.size / norm)


def _fit3(fm: float, f0: float, fp: float) -> tuple[float, float]:
    """Sub-sample offset and log-curvature of a peak from three samples.

    Returns ``(delta, q)`` with ``q = d^2 ln f / dx^2`` (0 for the parabolic
    fallback).
    """
    if fm > 0.0 and f0 > 0.0 and fp > 0.0:
        lm, l0, lp = math.log(fm), math.log(f0), math.log(fp)
        q = lm - 2.0 * l0 + lp
        if q < 0.0:
            return float(np.clip(0.5 * (lm - lp) / q, -1.0, 1.0)), q
    den = fm - 2.0 * f0 + fp
    if den < 0.0:
        return float(np.clip(0.5 * (fm - fp) / den, -1.0, 1.0)), 0.0
    return 0.0, 0.0


def _signed(index: int, size: int) -> int:
    return index - size if index > size // 2 else index


def _refine_peak(surface: np.ndarray, iy: int, ix: int) -> tuple[float, float, float]:
    """Sub-pixel ``(dy, dx, height)`` of the circular surface's maximum at ``[iy, ix]``."""
    h, w = surface.shape
    f0 = float(surface[iy, ix])
    ddy, qy = _fit3(float(surface[(iy - 1) % h, ix]), f0, float(surface[(iy + 1) % h, ix]))
    ddx, qx = _fit3(float(surface[iy, (ix - 1) % w]), f0, float(surface[iy, (ix + 1) % w]))
    # Height of the fitted Gaussian at its maximum (f0 for the parabolic fallback).
    height = f0 * math.exp(-0.5 * (qy * ddy * ddy + qx * ddx * ddx))
    return _signed(iy, h) + ddy, _signed(ix, w) + ddx, float(np.clip(height, 0.0, 1.0))


def _locate_peak(surface: np.ndarray, *, subpixel: bool) -> tuple[float, float, float]:
    """Return ``(dy, dx, height)`` of the maximum of a circular correlation surface."""
    iy, ix = (int(v) for v in np.unravel_index(int(np.argmax(surface)), surface.shape))
    if subpixel:
        return _refine_peak(surface, iy, ix)
    height = float(np.clip(surface[iy, ix], 0.0, 1.0))
    return float(_signed(iy, surface.shape[0])), float(_signed(ix, surface.shape[1])), height


# --------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------


def phase_correlation(a: np.ndarray, b: np.ndarray, *, upsample: bool = True) -> Shift:
    """Translation between two images by phase correlation.

    Parameters
    ----------
    a, b : numpy.ndarray
        2-D float images of the same shape; NaN marks nodata.
    upsample : bool
        Refine the integer correlation maximum to sub-pixel precision
        (3-point Gaussian/parabolic fit per axis); if False the shift is
        integer.

    Returns
    -------
    Shift
        ``(dx, dy)`` = ``p_b - p_a`` (``b(x + dx, y + dy) ~= a(x, y)``), and
        the normalised peak height in ``[0, 1]``.  The correlation is
        circular, so shifts are reported in ``[-size/2, size/2]`` (pad the
        images with NaN to measure larger ones).  NaN shift and peak 0 when
        either image has no finite texture.

    Raises
    ------
    ValueError
        If the images are not 2-D arrays of the same shape.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.ndim != 2 or a.shape != b.shape:
        raise ValueError(f"a and b must be 2-D arrays of equal shape, got {a.shape} and {b.shape}")
    window = _hann_separable(a.shape)
    return _shift_prepared(_apodise(a, window), b, window, subpixel=upsample)


def _shift_prepared(
    pa: np.ndarray | None, b: np.ndarray, window: np.ndarray, *, subpixel: bool = True
) -> Shift:
    """:func:`phase_correlation` with ``a`` already apodised (``pa``)."""
    pb = _apodise(b, window)
    if pa is None or pb is None:
        return Shift(math.nan, math.nan, 0.0)
    surface = _correlation_surface(pa, pb)
    dy, dx, height = _locate_peak(surface, subpixel=subpixel)
    return Shift(dx=dx, dy=dy, peak=height)


def _log_polar(magnitude: np.ndarray, radii: np.ndarray, n_angles: int) -> np.ndarray:
    """Resample a centred (fftshifted) square spectrum to (angle in [0, pi), log radius)."""
    n = magnitude.shape[0]
    centre = n // 2
    phi = np.arange(n_angles) * (np.pi / n_angles)
    rows = centre + np.sin(phi)[:, None] * radii[None, :]
    cols = centre + np.cos(phi)[:, None] * radii[None, :]
    return ndimage.map_coordinates(magnitude, [rows, cols], order=1, mode="nearest")


def _spectrum(prepared: np.ndarray) -> np.ndarray:
    """High-pass filtered log-magnitude spectrum, DC at ``[n//2, n//2]``."""
    n = prepared.shape[0]
    mag = np.abs(np.fft.fftshift(np.fft.fft2(prepared)))
    mag = np.log1p(mag / max(float(mag.mean()), 1e-300))
    f = (np.arange(n) - n // 2) / n
    cos_term = np.cos(np.pi * f)[:, None] * np.cos(np.pi * f)[None, :]
    highpass = (1.0 - cos_term) * (2.0 - cos_term)
    return mag * highpass


def _pad_square(image: np.ndarray, size: int) -> np.ndarray:
    """Centre ``image`` in a NaN-filled ``size`` x ``size`` array."""
    out = np.full((size, size), np.nan)
    h, w = image.shape
    r0 = (size - h) // 2
    c0 = (size - w) // 2
    out[r0 : r0 + h, c0 : c0 + w] = image
    return out


def _local_maxima(
    surface: np.ndarray, allowed: np.ndarray, count: int
) -> list[tuple[int, int]]:
    """Indices of the ``count`` highest local maxima (circular 5x5) inside ``allowed``."""
    peaks = (surface == ndimage.maximum_filter(surface, size=5, mode="wrap")) & allowed
    idx = np.flatnonzero(peaks)
    if idx.size == 0:
        return []
    order = idx[np.argsort(surface.ravel()[idx])[::-1][:count]]
    return [tuple(int(v) for v in np.unravel_index(i, surface.shape)) for i in order]


def _rotation_scale(
    a: np.ndarray, b: np.ndarray, min_scale: float, max_scale: float, *, count: int = 1
) -> list[tuple[float, float, float]]:
    """Fourier-Mellin candidates ``(theta_math, scale, peak)``, best first.

    ``theta_math`` is the angle of the linear map ``p_b = s R(theta) p_a`` with
    ``R`` the standard rotation matrix in (x, y); it is only defined modulo pi.
    Returns an empty list when either image has no texture.
    """
    size = max(a.shape + b.shape)
    size += size % 2
    window = _tukey_radial((size, size))
    pa = _apodise(_pad_square(a, size), window)
    pb = _apodise(_pad_square(b, size), window)
    if pa is None or pb is None:
        return []
    sa = _spectrum(pa)
    sb = _spectrum(pb)

    n_angles = max(size, 360)
    n_radii = size
    r_max = 0.5 * size - 1.0
    r_min = max(2.0, size / 64.0)
    log_step = math.log(r_max / r_min) / (n_radii - 1)
    radii = r_min * np.exp(np.arange(n_radii) * log_step)
    lpa = _log_polar(sa, radii, n_angles)
    lpb = _log_polar(sb, radii, n_angles)

    # Taper along log-radius only: the angle axis is periodic (period pi).
    taper = np.hanning(n_radii + 2)[1:-1][None, :]
    lpa = (lpa - lpa.mean()) * taper
    lpb = (lpb - lpb.mean()) * taper
    surface = _correlation_surface(lpa, lpb)

    # |B|(rho, phi) = s^2 |A|(s rho, phi - theta): lp_b is lp_a shifted by
    # +theta along angle and by -ln(s) along log-radius.
    shifts = np.array([_signed(i, n_radii) for i in range(n_radii)], dtype=np.float64)
    lo = -math.log(max_scale) / log_step - 1.0
    hi = -math.log(min_scale) / log_step + 1.0
    allowed = np.broadcast_to(((shifts >= lo) & (shifts <= hi))[None, :], surface.shape)
    out = []
    for iy, ix in _local_maxima(surface, allowed, count):
        d_angle, d_logr, height = _refine_peak(surface, iy, ix)
        theta = d_angle * math.pi / n_angles
        scale = math.exp(-d_logr * log_step)
        if min_scale * 0.99 <= scale <= max_scale * 1.01:
            out.append((theta, scale, height))
    return out


def estimate_similarity(
    a: np.ndarray, b: np.ndarray, *, min_scale: float = 0.5, max_scale: float = 2.0
) -> Similarity:
    """Estimate the rotation, scale and translation from ``a`` to ``b`` (Fourier-Mellin).

    1. The high-pass filtered log-magnitude spectra of the (radially
       windowed, zero-padded to a common square) images are resampled to
       log-polar coordinates (angle in ``[0, pi)`` x log radius) and phase
       correlated: the shift along angle is the rotation (modulo pi), the
       shift along log radius is ``-ln(scale)``.  The search is restricted to
       ``[min_scale, max_scale]``.
    2. The three highest correlation maxima are kept as candidates, each with
       its two 180-degree alternatives.  For each, ``b`` is warped back into
       the geometry of ``a`` (bilinear, about the image centres, on a grid
       that extends ``a`` by a quarter of its size on every side) and the
       translation is found by phase correlation; the candidate with the
       highest translation peak wins.
    3. The residual rotation/scale between ``a`` and the warped-back ``b`` is
       measured again (up to twice) and composed with the estimate, which
       removes most of the bias of step 1.

    Parameters
    ----------
    a, b : numpy.ndarray
        2-D float images (shapes may differ); NaN marks nodata.
    min_scale, max_scale : float
        Range of scale factors searched (``b`` pixels per ``a`` pixel).

    Returns
    -------
    Similarity
        ``matrix`` maps ``a`` pixel ``(x, y)`` to ``b`` pixel coordinates,
        ``matrix[:, :2] = scale * [[cos, sin], [-sin, cos]](angle)`` (angle
        counter-clockwise positive as displayed with y down).  When either
        image has no texture the matrix, scale and angle are NaN and the
        peak is 0.

    Raises
    ------
    ValueError
        If the inputs are not 2-D or the scale range is invalid.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.ndim != 2 or b.ndim != 2:
        raise ValueError(f"a and b must be 2-D, got shapes {a.shape} and {b.shape}")
    if not (0.0 < min_scale <= max_scale):
        raise ValueError(f"invalid scale range [{min_scale}, {max_scale}]")
    failed = Similarity(np.full((2, 3), np.nan), math.nan, math.nan, 0.0)
    candidates = _rotation_scale(a, b, min_scale, max_scale, count=_CANDIDATES)
    if not candidates:
        return failed

    ha, wa = a.shape
    hb, wb = b.shape
    centre_a = np.array([(wa - 1) / 2.0, (ha - 1) / 2.0])
    centre_b = np.array([(wb - 1) / 2.0, (hb - 1) / 2.0])
    # The translation is measured on a grid that extends a's frame by a
    # quarter of its size on every side, so that shifts up to 3/4 of the
    # image size (overlaps down to 1/4) are unambiguous.
    pad_y, pad_x = ha // 4, wa // 4
    a_ext = np.full((ha + 2 * pad_y, wa + 2 * pad_x), np.nan)
    a_ext[pad_y : pad_y + ha, pad_x : pad_x + wa] = a
    window_ext = _hann_separable(a_ext.shape)
    pa_ext = _apodise(a_ext, window_ext)
    ys, xs = np.mgrid[0 : a_ext.shape[0], 0 : a_ext.shape[1]].astype(np.float64)
    rel = np.stack([xs - pad_x - centre_a[0], ys - pad_y - centre_a[1]])

    def warp_back(lin: np.ndarray) -> np.ndarray:
        # b warped into a's (extended) geometry, rotating about the centres:
        # b_u(p) = b(lin @ (p - centre_a) + centre_b).
        bx = lin[0, 0] * rel[0] + lin[0, 1] * rel[1] + centre_b[0]
        by = lin[1, 0] * rel[0] + lin[1, 1] * rel[1] + centre_b[1]
        return sample(b, bx, by, method="bilinear")

    def translate(lin: np.ndarray) -> tuple[np.ndarray, float] | None:
        shift = _shift_prepared(pa_ext, warp_back(lin), window_ext)
        if not np.isfinite(shift.dx):
            return None
        # b_u(p + d) = a(p)  =>  p_b = lin @ p_a + lin @ (d - centre_a) + centre_b
        d = np.array([shift.dx, shift.dy])
        return np.column_stack([lin, lin @ (d - centre_a) + centre_b]), shift.peak

    best: tuple[np.ndarray, float] | None = None
    for theta0, scale, _ in candidates:
        for theta in (theta0, theta0 + math.pi):
            found = translate(_similarity_linear(scale, theta))
            if found is not None and (best is None or found[1] > best[1]):
                best = found
    if best is None:
        return failed

    # Refinement: the residual rotation/scale between a and b warped back is
    # measured again (both now have the same geometry, which removes most of
    # the bias of the first estimate); kept unless the peak drops noticeably.
    for _ in range(_REFINE_ITERATIONS):
        residual = _rotation_scale(
            a, warp_back(best[0][:, :2])[pad_y : pad_y + ha, pad_x : pad_x + wa], 1.0 / 1.1, 1.1
        )
        if not residual or abs(residual[0][0]) > math.radians(5.0):
            break
        lin = best[0][:, :2] @ _similarity_linear(residual[0][1], residual[0][0])
        found = translate(lin)
        if found is None or found[1] < _REFINE_TOLERANCE * best[1]:
            break
        best = found

    matrix, peak = best
    scale = float(math.hypot(matrix[0, 0], matrix[1, 0]))
    angle = -math.atan2(matrix[1, 0], matrix[0, 0])  # in [-pi, pi)
    if angle == -math.pi:
        angle = math.pi
    return Similarity(matrix=matrix, scale=scale, angle=float(angle), peak=float(peak))


def _similarity_linear(scale: float, theta: float) -> np.ndarray:
    """``scale * R(theta)`` with ``R`` the standard (x, y) rotation matrix."""
    c, s = math.cos(theta), math.sin(theta)
    return scale * np.array([[c, -s], [s, c]])
