"""Point sampling (interpolation) of single- and multi-band images.

The image is sampled at arbitrary pixel coordinates ``(x, y)`` given in the
image's own frame, with the pixel-centre convention of ``CONVENTIONS.md``:
the centre of pixel ``image[..., r, c]`` is at ``x = c``, ``y = r``.

Nodata is NaN.  A sample is NaN when its position is not finite, when it
needs a pixel outside the image, or when any tap with a non-zero weight is
NaN (per band).  Taps whose weight is exactly zero are never read, so, for
example, bilinear sampling exactly on the last row or column works, and every
method reproduces the pixel values exactly at integer positions.

Methods and their taps (``x0 = floor(x)``, ``f = x - x0``, same along y):

``nearest``
    one tap at ``floor(x + 0.5)`` (round half up).
``bilinear``
    2 taps ``x0, x0 + 1`` with weights ``1 - f, f``.
``cubic``
    4 taps ``x0 - 1 .. x0 + 2``, Keys' cubic convolution kernel with
    ``a = -0.5``.
``lanczos``
    6 taps ``x0 - 2 .. x0 + 3``, Lanczos kernel with ``a = 3``, weights
    normalised to sum to one along each axis (from :data:`LANCZOS_TABLE`,
    linear between its 4,096 fractions of a pixel: within 2.6e-8).

The numba kernels (:func:`sample`) loop over the sample points; the tap
weights of a point are computed once and reused for every band.
:func:`sample_reference` is a vectorised numpy implementation of the same
rules, kept for the tests.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["LANCZOS_TABLE", "METHODS", "lanczos_weights", "sample", "sample_reference", "window_for"]

METHODS = ("nearest", "bilinear", "cubic", "lanczos")

# Half width of the kernels: taps are floor(x) - (half - 1) .. floor(x) + half
# (nearest: the single tap floor(x + 0.5)).
_HALF = {"nearest": 0, "bilinear": 1, "cubic": 2, "lanczos": 3}

_CUBIC_A = -0.5
_LANCZOS_A = 3


# --------------------------------------------------------------------------
# numba kernels
# --------------------------------------------------------------------------


@numba.njit(nogil=True, cache=True)
def _set_nan(out, p):  # pragma: no cover - compiled
    for b in range(out.shape[0]):
        out[b, p] = np.nan


@numba.njit(nogil=True, cache=True)
def _accumulate(image, out, p, r0, c0, wy, wx):  # pragma: no cover - compiled
    """Write the separable weighted sum of the taps at ``(r0.., c0..)`` to ``out[:, p]``."""
    nbands, height, width = image.shape
    ntaps = wx.shape[0]
    # Every tap with a non-zero weight must be inside the image (the weights
    # along each axis sum to one, so the other axis always has a non-zero tap).
    for j in range(ntaps):
        if wy[j] != 0.0:
            r = r0 + j
            if r < 0 or r >= height:
                _set_nan(out, p)
                return
    for i in range(ntaps):
        if wx[i] != 0.0:
            c = c0 + i
            if c < 0 or c >= width:
                _set_nan(out, p)
                return
    for b in range(nbands):
        acc = 0.0
        for j in range(ntaps):
            wyj = wy[j]
            if wyj == 0.0:
                continue
            r = r0 + j
            row = 0.0
            for i in range(ntaps):
                wxi = wx[i]
                if wxi == 0.0:
                    continue
                row += wxi * image[b, r, c0 + i]
            acc += wyj * row
        out[b, p] = acc


@numba.njit(nogil=True, cache=True)
def _sample_nearest(image, x, y, out):  # pragma: no cover - compiled
    _, height, width = image.shape
    w = np.ones(1)
    for p in range(x.shape[0]):
        xp = x[p]
        yp = y[p]
        # Comparisons are False for NaN, so this also rejects non-finite points.
        if not (xp > -2.0 and xp < width + 1.0 and yp > -2.0 and yp < height + 1.0):
            _set_nan(out, p)
            continue
        c = int(math.floor(xp + 0.5))
        r = int(math.floor(yp + 0.5))
        _accumulate(image, out, p, r, c, w, w)


@numba.njit(nogil=True, cache=True)
def bilinear_taps(im, r, c, wy0, wy1, wx0, wx1):  # pragma: no cover - compiled
    """``sum_j wy_j (sum_i wx_i im[r + j, c + i])`` over the 2 x 2 taps, skipping zero weights.

    The arithmetic of :func:`_accumulate` for two taps per axis, written out (2-D ``im``).
    """
    if wx0 != 0.0 and wx1 != 0.0 and wy0 != 0.0 and wy1 != 0.0:  # the usual case: the same sums, no tests
        return wy0 * (wx0 * im[r, c] + wx1 * im[r, c + 1]) + wy1 * (wx0 * im[r + 1, c] + wx1 * im[r + 1, c + 1])
    acc = 0.0
    if wy0 != 0.0:
        row = 0.0
        if wx0 != 0.0:
            row += wx0 * im[r, c]
        if wx1 != 0.0:
            row += wx1 * im[r, c + 1]
        acc += wy0 * row
    if wy1 != 0.0:
        row = 0.0
        if wx0 != 0.0:
            row += wx0 * im[r + 1, c]
        if wx1 != 0.0:
            row += wx1 * im[r + 1, c + 1]
        acc += wy1 * row
    return acc


@numba.njit(nogil=True, cache=True)
def _bilinear_point(image, out, p, xp, yp):  # pragma: no cover - compiled
    """General bilinear sample of point ``p`` (edges, integral positions, outside)."""
    nbands, height, width = image.shape
    if not (xp > -3.0 and xp < width + 2.0 and yp > -3.0 and yp < height + 2.0):
        _set_nan(out, p)
        return
    x0 = math.floor(xp)
    y0 = math.floor(yp)
    fx = xp - x0
    fy = yp - y0
    c = int(x0)
    r = int(y0)
    wx0, wx1, wy0, wy1 = 1.0 - fx, fx, 1.0 - fy, fy
    # every tap with a non-zero weight must be inside the image
    if (wy0 != 0.0 and (r < 0 or r >= height)) or (wy1 != 0.0 and (r + 1 < 0 or r + 1 >= height)) \
            or (wx0 != 0.0 and (c < 0 or c >= width)) or (wx1 != 0.0 and (c + 1 < 0 or c + 1 >= width)):
        _set_nan(out, p)
        return
    for b in range(nbands):
        out[b, p] = bilinear_taps(image[b], r, c, wy0, wy1, wx0, wx1)


@numba.njit(nogil=True, cache=True)
def _sample_bilinear(image, x, y, out):  # pragma: no cover - compiled
    nbands, height, width = image.shape
    for p in range(x.shape[0]):
        xp = x[p]
        yp = y[p]
        # the usual case first, kept free of the general code so that it compiles tight:
        # inside, and all four taps weigh (the same sums as bilinear_taps)
        if xp > 0.0 and xp < width - 1 and yp > 0.0 and yp < height - 1:
            x0 = math.floor(xp)
            y0 = math.floor(yp)
            fx = xp - x0
            fy = yp - y0
            wx0, wx1, wy0, wy1 = 1.0 - fx, fx, 1.0 - fy, fy
            if wx0 != 0.0 and wx1 != 0.0 and wy0 != 0.0 and wy1 != 0.0:
                c = int(x0)
                r = int(y0)
                for b in range(nbands):
                    out[b, p] = wy0 * (wx0 * image[b, r, c] + wx1 * image[b, r, c + 1]) \
                        + wy1 * (wx0 * image[b, r + 1, c] + wx1 * image[b, r + 1, c + 1])
                continue
        _bilinear_point(image, out, p, xp, yp)


@numba.njit(nogil=True, cache=True)
def _sample_affine_bilinear(image, x, y, jac, offsets, out):  # pragma: no cover - compiled
    """``out[:, i P + k]`` = the bilinear sample at ``(x_i, y_i) + jac_i @ offsets_k`` (P offsets)."""
    npatch = offsets.shape[0]
    px = np.empty(npatch)
    py = np.empty(npatch)
    for i in range(x.shape[0]):
        for k in range(npatch):
            # the sums in the order numpy's broadcasting of x + j00 u + j01 v takes them
            px[k] = x[i] + jac[i, 0, 0] * offsets[k, 0] + jac[i, 0, 1] * offsets[k, 1]
            py[k] = y[i] + jac[i, 1, 0] * offsets[k, 0] + jac[i, 1, 1] * offsets[k, 1]
        _sample_bilinear(image, _onto_edge(px, image.shape[2]), _onto_edge(py, image.shape[1]),
                         out[:, i * npatch : (i + 1) * npatch])


def sample_affine_patches(image: np.ndarray, x: np.ndarray, y: np.ndarray, jac: np.ndarray,
                          offsets: np.ndarray) -> np.ndarray:
    """Bilinear patches at ``(x_i, y_i) + jac_i @ offsets_k``, one patch at a time.

    The same values as :func:`sample` (``method="bilinear"``) of those positions, without the
    (n, P) position arrays: a patch's positions are formed, sampled and dropped in turn.

    Parameters
    ----------
    image : numpy.ndarray
        2-D image (sampled as float32), NaN marks nodata.
    x, y : numpy.ndarray
        Patch centres, shape (n,).
    jac : numpy.ndarray
        Shape (n, 2, 2): rows ``d(x, y) / d(u, v)`` of each patch.
    offsets : numpy.ndarray
        Shape (P, 2): the template offsets ``(u, v)``.

    Returns
    -------
    numpy.ndarray
        float32, shape (n, P); NaN where :func:`sample` gives NaN.
    """
    image3 = np.ascontiguousarray(np.asarray(image, dtype=np.float32))[None]
    xf = np.ascontiguousarray(x, dtype=np.float64).ravel()
    yf = np.ascontiguousarray(y, dtype=np.float64).ravel()
    jf = np.ascontiguousarray(jac, dtype=np.float64).reshape(-1, 2, 2)
    of = np.ascontiguousarray(offsets, dtype=np.float64).reshape(-1, 2)
    if not (xf.shape == yf.shape and jf.shape[0] == xf.shape[0]):
        raise ValueError(f"x {xf.shape}, y {yf.shape} and jac {jf.shape} do not describe the same patches")
    out = np.empty((1, xf.shape[0] * of.shape[0]), dtype=np.float32)
    _sample_affine_bilinear(image3, xf, yf, jf, of, out)
    return out.reshape(xf.shape[0], of.shape[0])


@numba.njit(nogil=True, cache=True)
def _keys_weights(f, a, w):  # pragma: no cover - compiled
    """Keys cubic weights of the taps at distances ``f + 1, f, 1 - f, 2 - f``."""
    for k in range(4):
        d = abs(f - (k - 1))
        if d <= 1.0:
            w[k] = ((a + 2.0) * d - (a + 3.0)) * d * d + 1.0
        elif d < 2.0:
            w[k] = ((a * d - 5.0 * a) * d + 8.0 * a) * d - 4.0 * a
        else:
            w[k] = 0.0


@numba.njit(nogil=True, cache=True)
def _sample_cubic(image, x, y, out):  # pragma: no cover - compiled
    _, height, width = image.shape
    wx = np.empty(4)
    wy = np.empty(4)
    for p in range(x.shape[0]):
        xp = x[p]
        yp = y[p]
        if not (xp > -4.0 and xp < width + 3.0 and yp > -4.0 and yp < height + 3.0):
            _set_nan(out, p)
            continue
        x0 = math.floor(xp)
        y0 = math.floor(yp)
        _keys_weights(xp - x0, _CUBIC_A, wx)
        _keys_weights(yp - y0, _CUBIC_A, wy)
        _accumulate(image, out, p, int(y0) - 1, int(x0) - 1, wy, wx)


def _lanczos_table(steps: int) -> np.ndarray:
    """Normalised Lanczos-3 weights of the taps ``floor(x) - 2 .. floor(x) + 3`` at the
    fractions ``f = i / steps``, shape ``(steps + 1, 6)``."""
    d = np.arange(steps + 1)[:, None] / steps - np.arange(-2, 4)[None, :]
    w = np.sinc(d) * np.sinc(d / _LANCZOS_A)
    return w / w.sum(axis=1, keepdims=True)


#: Lanczos-3 weights at 4,096 fractions of a pixel (rows), for :func:`lanczos_weights`.
LANCZOS_TABLE = _lanczos_table(4096)


@numba.njit(nogil=True, cache=True, inline="always")
def lanczos_weights(f, table, w):  # pragma: no cover - compiled
    """The six Lanczos-3 weights at the fraction ``f`` in [0, 1), linear between the rows of
    ``table`` (:data:`LANCZOS_TABLE`: within 2.6e-8 of the kernel). :func:`sample` took
    360-450 ms for a 1024 tile's 1.17 M positions with the kernel's sines per point, 157-167 ms
    with the table; the every-pixel pass's own loop 29-36 ms."""
    n = table.shape[0] - 1
    t = f * n
    i = min(int(t), n - 1)
    a = t - i
    for k in range(6):
        w[k] = table[i, k] + a * (table[i + 1, k] - table[i, k])


@numba.njit(nogil=True, cache=True, inline="always")
def _lanczos_at(f, table, w):  # pragma: no cover - compiled
    if f == 0.0:  # exactly on a pixel: one tap, the others never read
        for k in range(6):
            w[k] = 0.0
        w[2] = 1.0
    else:
        lanczos_weights(f, table, w)


@numba.njit(nogil=True, cache=True)
def _sample_lanczos(image, x, y, table, out):  # pragma: no cover - compiled
    _, height, width = image.shape
    wx = np.empty(6)
    wy = np.empty(6)
    for p in range(x.shape[0]):
        xp = x[p]
        yp = y[p]
        if not (xp > -5.0 and xp < width + 4.0 and yp > -5.0 and yp < height + 4.0):
            _set_nan(out, p)
            continue
        x0 = math.floor(xp)
        y0 = math.floor(yp)
        _lanczos_at(xp - x0, table, wx)
        _lanczos_at(yp - y0, table, wy)
        _accumulate(image, out, p, int(y0) - 2, int(x0) - 2, wy, wx)


def _sample_lanczos_table(image, x, y, out):
    _sample_lanczos(image, x, y, LANCZOS_TABLE, out)


_KERNELS = {
    "nearest": _sample_nearest,
    "bilinear": _sample_bilinear,
    "cubic": _sample_cubic,
    "lanczos": _sample_lanczos_table,
}


# --------------------------------------------------------------------------
# Python front end
# --------------------------------------------------------------------------


def _check_method(method: str) -> None:
    if method not in METHODS:
        raise ValueError(f"unknown resampling method {method!r}; expected one of {METHODS}")


def _prepare(
    image: np.ndarray, x: np.ndarray, y: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool, tuple[int, ...]]:
    """Validate inputs; return a 3-D image, flat float64 x/y, a 2-D flag and the point shape."""
    image = np.asarray(image)
    if image.ndim not in (2, 3):
        raise ValueError(f"image must be 2-D (y, x) or 3-D (band, y, x), got shape {image.shape}")
    if image.dtype not in (np.float32, np.float64):
        image = image.astype(np.float64)
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.shape != y.shape:
        raise ValueError(f"x and y must have the same shape, got {x.shape} and {y.shape}")
    is_2d = image.ndim == 2
    image3 = image[np.newaxis] if is_2d else image
    height, width = image3.shape[-2:]
    return image3, _onto_edge(x.ravel(), width), _onto_edge(y.ravel(), height), is_2d, x.shape


#: Positions at most this far (pixels) outside the first or last pixel centre are moved onto
#: it: a fitted mapping's round-off (an identity fit gives 1e-5 px) must not leave the edge
#: pixels of two aligned images without a value.
EDGE = 1e-3


@numba.njit(nogil=True, cache=True)
def _onto_edge(v, size):  # pragma: no cover - compiled
    """A copy of ``v`` (1-D float64) with the positions within :data:`EDGE` outside ``[0, size - 1]`` moved onto it."""
    out = np.empty_like(v)
    last = float(size - 1)
    for i in range(v.shape[0]):
        a = v[i]
        if a < 0.0 and a >= -EDGE:
            a = 0.0
        elif a > last and a <= last + EDGE:
            a = last
        out[i] = a
    return out


def sample(
    image: np.ndarray, x: np.ndarray, y: np.ndarray, *, method: str = "bilinear"
) -> np.ndarray:
    """Interpolate an image at arbitrary pixel positions (numba).

    Parameters
    ----------
    image : numpy.ndarray
        float32 or float64 image, shape ``(band, H, W)`` or ``(H, W)``;
        NaN marks nodata.  Other dtypes are converted to float64.
    x, y : numpy.ndarray
        Sample positions (column, row) in the image's pixel-centre frame, of
        any equal shape.
    method : {"nearest", "bilinear", "cubic", "lanczos"}
        Interpolation kernel (see the module docstring).

    Returns
    -------
    numpy.ndarray
        float32 array of shape ``(band, *x.shape)`` (``x.shape`` for a 2-D
        image).  NaN where the position is not finite, where a tap with a
        non-zero weight falls outside the image, or where such a tap is NaN.

    Raises
    ------
    ValueError
        On an unknown method, a wrong image rank or mismatched ``x``/``y``.
    """
    _check_method(method)
    image3, xf, yf, is_2d, pshape = _prepare(image, x, y)
    image3 = np.ascontiguousarray(image3)
    out = np.empty((image3.shape[0], xf.shape[0]), dtype=np.float32)
    _KERNELS[method](image3, np.ascontiguousarray(xf), np.ascontiguousarray(yf), out)
    out = out.reshape((image3.shape[0],) + pshape)
    return out[0] if is_2d else out


# --------------------------------------------------------------------------
# numpy reference
# --------------------------------------------------------------------------


def _weights_reference(method: str, coord: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised tap indices ``(n, taps)`` and weights ``(n, taps)`` along one axis."""
    if method == "nearest":
        idx = np.floor(coord + 0.5)[:, None]
        return idx, np.ones_like(idx)
    base = np.floor(coord)
    f = (coord - base)[:, None]
    half = _HALF[method]
    offsets = np.arange(-(half - 1), half + 1, dtype=np.float64)[None, :]
    idx = base[:, None] + offsets
    d = np.abs(f - offsets)
    if method == "bilinear":
        w = np.clip(1.0 - d, 0.0, None)
    elif method == "cubic":
        a = _CUBIC_A
        near = ((a + 2.0) * d**3) - ((a + 3.0) * d**2) + 1.0
        far = a * d**3 - 5.0 * a * d**2 + 8.0 * a * d - 4.0 * a
        w = np.where(d <= 1.0, near, np.where(d < 2.0, far, 0.0))
    else:  # lanczos
        a = _LANCZOS_A
        w = np.where(d < a, np.sinc(d) * np.sinc(d / a), 0.0)
        w = w / w.sum(axis=1, keepdims=True)
        exact = (f[:, 0] == 0.0)[:, None]
        w = np.where(exact, (offsets == 0.0).astype(np.float64), w)
    return idx, w


def sample_reference(
    image: np.ndarray, x: np.ndarray, y: np.ndarray, *, method: str = "bilinear"
) -> np.ndarray:
    """Vectorised numpy implementation of :func:`sample` (for tests).

    Parameters
    ----------
    image : numpy.ndarray
        Image, shape ``(band, H, W)`` or ``(H, W)``; NaN marks nodata.
    x, y : numpy.ndarray
        Sample positions of any equal shape.
    method : {"nearest", "bilinear", "cubic", "lanczos"}
        Interpolation kernel.

    Returns
    -------
    numpy.ndarray
        float32 array, same shape and NaN rules as :func:`sample`.
    """
    _check_method(method)
    image3, xf, yf, is_2d, pshape = _prepare(image, x, y)
    nbands, height, width = image3.shape
    n = xf.shape[0]
    finite = np.isfinite(xf) & np.isfinite(yf)
    xs = np.where(finite, xf, 0.0)
    ys = np.where(finite, yf, 0.0)
    # Clamp far-away points (they are NaN anyway) so the index arithmetic is safe.
    xs = np.clip(xs, -10.0, width + 10.0)
    ys = np.clip(ys, -10.0, height + 10.0)
    cidx, wx = _weights_reference(method, xs)
    ridx, wy = _weights_reference(method, ys)
    bad = ~finite
    bad |= np.any((wx != 0.0) & ((cidx < 0) | (cidx >= width)), axis=1)
    bad |= np.any((wy != 0.0) & ((ridx < 0) | (ridx >= height)), axis=1)
    ci = np.clip(cidx, 0, width - 1).astype(np.intp)
    ri = np.clip(ridx, 0, height - 1).astype(np.intp)
    out = np.empty((nbands, n), dtype=np.float32)
    w2 = wy[:, :, None] * wx[:, None, :]  # (n, ty, tx)
    used = w2 != 0.0
    for b in range(nbands):  # loop over bands only; points are vectorised
        vals = image3[b][ri[:, :, None], ci[:, None, :]].astype(np.float64)
        vals = np.where(used, vals, 0.0)
        res = np.sum(w2 * vals, axis=(1, 2))
        out[b] = np.where(bad, np.nan, res)
    out = out.reshape((nbands,) + pshape)
    return out[0] if is_2d else out


# --------------------------------------------------------------------------
# windows
# --------------------------------------------------------------------------


def window_for(
    x: np.ndarray, y: np.ndarray, *, method: str, shape: tuple[int, int]
) -> tuple[int, int, int, int] | None:
    """Bounding window of the source pixels needed to sample at ``(x, y)``.

    Parameters
    ----------
    x, y : numpy.ndarray
        Sample positions (any shape); non-finite entries are ignored.
    method : {"nearest", "bilinear", "cubic", "lanczos"}
        Interpolation kernel, which sets the tap margin.
    shape : tuple of int
        ``(H, W)`` of the full image.

    Returns
    -------
    tuple of int or None
        ``(row0, row1, col0, col1)``, half open, clipped to the image, such
        that ``sample(image[..., row0:row1, col0:col1], x - col0, y - row0)``
        equals ``sample(image, x, y)``.  None when there is no finite point
        or no point has any tap inside the image.
    """
    _check_method(method)
    height, width = int(shape[-2]), int(shape[-1])
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    finite = np.isfinite(x) & np.isfinite(y)
    if not finite.any():
        return None
    xs = x[finite]
    ys = y[finite]
    half = _HALF[method]

    def span(lo: float, hi: float, size: int) -> tuple[int, int]:
        if method == "nearest":
            start = math.floor(lo + 0.5)
            stop = math.floor(hi + 0.5) + 1
        else:
            start = math.floor(lo) - (half - 1)
            stop = math.floor(hi) + half + 1
        return int(min(max(start, 0), size)), int(min(max(stop, 0), size))

    row0, row1 = span(float(ys.min()), float(ys.max()), height)
    col0, col1 = span(float(xs.min()), float(xs.max()), width)
    if row0 >= row1 or col0 >= col1:
        return None
    return row0, row1, col0, col1
