"""Helpers for tests and benchmarks (need the ``test`` extra)."""

from __future__ import annotations

import contextlib
import logging
import os
from typing import Iterator


@contextlib.contextmanager
def local_s3(bucket: str = "geocoder-test") -> Iterator[str]:
    """A local S3 server (moto) with one bucket; yields ``s3://bucket``.

    While it runs, the environment points fsspec (``FSSPEC_S3_ENDPOINT_URL``) and GDAL's
    ``/vsis3/`` at it, for this process and for every process started meanwhile (Dask
    workers, the CLI), as a deployment's environment points them at S3 or MinIO.
    """
    import fsspec
    import fsspec.config
    from moto.server import ThreadedMotoServer

    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    env = {
        "AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing", "AWS_DEFAULT_REGION": "us-east-1",
        "FSSPEC_S3_ENDPOINT_URL": f"http://{host}:{port}",
        "AWS_S3_ENDPOINT": f"{host}:{port}", "AWS_HTTPS": "NO", "AWS_VIRTUAL_HOSTING": "FALSE",
    }
    saved = {k: os.environ.get(k) for k in env}

    def reconfigure() -> None:
        fsspec.config.conf.clear()
        fsspec.config.set_conf_env(fsspec.config.conf)

    os.environ.update(env)
    reconfigure()
    try:
        fs, _ = fsspec.core.url_to_fs(f"s3://{bucket}", skip_instance_cache=True)
        fs.mkdir(bucket)
        yield f"s3://{bucket}"
    finally:
        server.stop()
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        reconfigure()


def textured_overlap(pair, *, rx: int = 25, ry: int = 3, noise: float = 0.02, precision: float = 0.1, margin: int = 2):
    """Base pixels where a match of the required precision is possible at all.

    The template (``2 rx + 1`` by ``2 ry + 1``) must lie inside both images, and the
    Cramer-Rao bound of its shift must be below ``precision``: with white noise of
    ``sigma_n`` in both images the shift covariance is ``2 sigma_n^2 N^-1``
    (``N = sum grad grad^T`` over the template), so the smallest eigenvalue of N must reach
    ``2 sigma_n^2 / precision^2``. N is taken from the noisy base with the expected noise
    part of the gradients (``sigma_n^2 / 2`` per pixel for central differences) removed.
    """
    import numpy as np
    import scipy.ndimage as ndi

    base = pair.base[0].astype(np.float64)
    lo, hi = np.nanpercentile(base, [1, 99])
    sn = noise * (hi - lo)
    h, w = pair.dx.shape
    hd, wd = pair.distorted.shape[1:]
    ys, xs = np.mgrid[0:h, 0:w]
    px, py = xs + pair.dx, ys + pair.dy
    inside = (px >= rx + margin) & (px < wd - rx - margin) & (py >= ry + margin) & (py < hd - ry - margin)
    inside &= (xs >= rx + margin) & (xs < w - rx - margin) & (ys >= ry + margin) & (ys < h - ry - margin)
    gy, gx = np.gradient(base)
    size = (2 * ry + 1, 2 * rx + 1)
    n = size[0] * size[1]
    # a template must not touch nodata (NaN) in the base
    valid = np.isfinite(gx) & np.isfinite(gy)
    gx, gy = np.where(valid, gx, 0.0), np.where(valid, gy, 0.0)
    inside &= ndi.uniform_filter(valid.astype(np.float64), size, mode="constant") > 1.0 - 0.5 / n
    sxx = ndi.uniform_filter(gx * gx, size) * n - n * sn**2 / 2
    syy = ndi.uniform_filter(gy * gy, size) * n - n * sn**2 / 2
    sxy = ndi.uniform_filter(gx * gy, size) * n
    lam_min = 0.5 * (sxx + syy) - np.sqrt(0.25 * (sxx - syy) ** 2 + sxy**2)
    return inside & (lam_min >= 2 * sn**2 / precision**2)


def distort_by_field(image, dx, dy, shape: tuple[int, int], *, method: str = "cubic",
                     iterations: int = 40, tol: float = 1e-4):
    """Render a distorted image whose true displacement field is a given dense field.

    The seed's error analysis (seed 003 sec. 14 a): an orthoimage on the base grid is
    distorted by the field a real registration produced, so that the base pixel ``p`` is
    seen in the new image at ``p + d(p)`` exactly. For every pixel ``q`` of the distorted
    grid, ``p + d(p) = q`` is solved by Newton's method (``d`` interpolated bilinearly, so it
    equals the given field at every base pixel; started from the inverse of the field's
    least-squares affine) and the image is sampled at ``p`` once with
    :func:`geocoder.kernels.resample.sample`.

    Parameters
    ----------
    image : numpy.ndarray
        ``(H, W)`` or ``(bands, H, W)`` image on the base grid; NaN is nodata.
    dx, dy : numpy.ndarray
        ``(H, W)`` field on the base grid (``p_distorted - p_base``), NaN where undefined.
    shape : tuple of int
        ``(Hd, Wd)`` of the distorted grid.
    method : str
        Interpolator of the sampling (see :func:`geocoder.kernels.resample.sample`).
    iterations : int
        Newton iterations at most.
    tol : float
        Convergence threshold (px) on ``|p + d(p) - q|`` in each axis.

    Returns
    -------
    distorted : numpy.ndarray
        float32 ``(Hd, Wd)`` (or ``(bands, Hd, Wd)``), NaN where ``q`` has no solution.
    truth_valid : numpy.ndarray
        bool ``(H, W)``: base pixels whose ``p + d(p)`` lies inside the distorted grid and
        leads back to ``p`` (the field is one-to-one there), i.e. where ``(dx, dy)`` is the
        true field of the new pair.
    """
    import numpy as np

    from geocoder.kernels.resample import sample

    dx = np.asarray(dx, dtype=np.float64)
    dy = np.asarray(dy, dtype=np.float64)
    if dx.shape != dy.shape or dx.ndim != 2:
        raise ValueError(f"dx and dy must be two (H, W) arrays of one shape, got {dx.shape} and {dy.shape}")
    img = np.asarray(image)
    if img.shape[-2:] != dx.shape:
        raise ValueError(f"image {img.shape} is not on the field's grid {dx.shape}")
    h, w = dx.shape
    hd, wd = (int(s) for s in shape)
    finite = np.isfinite(dx) & np.isfinite(dy)
    if finite.sum() < 3:
        raise ValueError("the field has fewer than 3 defined pixels")
    field = np.stack([dx, dy])
    gy_x, gx_x = np.gradient(dx)
    gy_y, gx_y = np.gradient(dy)
    partials = np.stack([gx_x, gy_x, gx_y, gy_y])

    ys, xs = np.nonzero(finite)
    step = max(1, ys.size // 20000)
    ys, xs = ys[::step].astype(np.float64), xs[::step].astype(np.float64)
    design = np.column_stack([xs, ys, np.ones_like(xs)])
    coef, *_ = np.linalg.lstsq(design, np.column_stack([xs + dx[finite][::step], ys + dy[finite][::step]]), rcond=None)
    a_inv = np.linalg.inv(coef[:2].T)
    shift = coef[2]

    def solve(qx: np.ndarray, qy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        px, py = a_inv @ np.stack([qx - shift[0], qy - shift[1]])
        out_x, out_y = np.full(qx.shape, np.nan), np.full(qx.shape, np.nan)
        idx = np.arange(qx.size)
        for _ in range(iterations):
            d = sample(field, px, py, method="bilinear").astype(np.float64)
            rx, ry = px + d[0] - qx[idx], py + d[1] - qy[idx]
            alive = np.isfinite(rx) & np.isfinite(ry)
            done = alive & (np.abs(rx) <= tol) & (np.abs(ry) <= tol)
            out_x[idx[done]], out_y[idx[done]] = px[done], py[done]
            keep = alive & ~done
            idx, px, py, rx, ry = idx[keep], px[keep], py[keep], rx[keep], ry[keep]
            if idx.size == 0:
                break
            g = sample(partials, px, py, method="bilinear").astype(np.float64)
            a, b, c, e = 1.0 + g[0], g[1], g[2], 1.0 + g[3]
            det = a * e - b * c
            ok = np.isfinite(det) & (det > 0.05)
            det = np.where(ok, det, 1.0)
            px = px - np.where(ok, (e * rx - b * ry) / det, rx)
            py = py - np.where(ok, (a * ry - c * rx) / det, ry)
        return out_x, out_y

    def solve_blocks(qx: np.ndarray, qy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # in blocks of points, so the scratch arrays stay small on large scenes
        px, py = np.empty_like(qx), np.empty_like(qy)
        for s in range(0, qx.size, 1 << 18):
            px[s : s + (1 << 18)], py[s : s + (1 << 18)] = solve(qx[s : s + (1 << 18)], qy[s : s + (1 << 18)])
        return px, py

    qy, qx = np.mgrid[0:hd, 0:wd].astype(np.float64)
    px, py = solve_blocks(qx.ravel(), qy.ravel())
    distorted = sample(img, px.reshape(hd, wd), py.reshape(hd, wd), method=method)

    by, bx = np.mgrid[0:h, 0:w].astype(np.float64)
    fx, fy = (bx + dx).ravel(), (by + dy).ravel()
    inside = np.isfinite(fx) & np.isfinite(fy) & (fx >= 0) & (fx <= wd - 1) & (fy >= 0) & (fy <= hd - 1)
    back_x, back_y = np.full(fx.shape, np.nan), np.full(fx.shape, np.nan)
    back_x[inside], back_y[inside] = solve_blocks(fx[inside], fy[inside])
    truth_valid = (np.abs(back_x - bx.ravel()) < 0.01) & (np.abs(back_y - by.ravel()) < 0.01)
    return distorted, truth_valid.reshape(h, w)


def field_errors(ds, true_dx, true_dy, mask=None) -> dict:
    """Accuracy of a register output's field against a known field, per status.

    Parameters
    ----------
    ds : xarray.Dataset
        A :func:`geocoder.register` output (``dx``, ``dy``, ``sigma_x``, ``sigma_y``,
        ``status``), or a mapping holding those arrays.
    true_dx, true_dy : numpy.ndarray
        The true field on the base grid.
    mask : numpy.ndarray, optional
        bool, base pixels to evaluate (default all); pixels with status ``OUTSIDE`` or a
        non-finite truth are never evaluated.

    Returns
    -------
    dict
        ``groups``: for ``matched``, ``filled``, ``estimated``, ``rest`` (the other statuses
        except outside) and ``all``, a tuple (share of the evaluated pixels, RMSE px, share
        off by more than 1 px; NaN when empty); ``calibration``: (RMSE_x / RMS(sigma_x),
        RMSE_y / RMS(sigma_y)) over the matched pixels; ``rms_sigma``: (RMS(sigma_x),
        RMS(sigma_y)) over them; ``rmse_xy``: (RMSE_x, RMSE_y) over them; ``pixels``: how many
        were evaluated.
    """
    import numpy as np

    from geocoder.status import Status

    def values(name):
        v = ds[name]
        return np.asarray(getattr(v, "values", v))

    st = values("status")
    ex, ey = values("dx") - true_dx, values("dy") - true_dy
    sx, sy = values("sigma_x"), values("sigma_y")
    evaluated = (st != Status.OUTSIDE) & np.isfinite(true_dx) & np.isfinite(true_dy)
    if mask is not None:
        evaluated &= np.asarray(mask, dtype=bool)
    err = np.hypot(ex, ey)
    n = int(evaluated.sum())
    core = [Status.MATCHED, Status.FILLED, Status.ESTIMATED]
    groups = {"matched": st == Status.MATCHED, "filled": st == Status.FILLED, "estimated": st == Status.ESTIMATED,
              "rest": ~np.isin(st, core), "all": np.ones(st.shape, dtype=bool)}
    out: dict = {"groups": {}, "pixels": n}
    for name, m in groups.items():
        e = err[m & evaluated]
        out["groups"][name] = ((e.size / n) if n else np.nan, float(np.sqrt(np.mean(e**2))) if e.size else np.nan,
                               float(np.mean(e > 1.0)) if e.size else np.nan)
    m = groups["matched"] & evaluated
    if m.any():
        rmse = tuple(float(np.sqrt(np.mean(e[m] ** 2))) for e in (ex, ey))
        rms_s = tuple(float(np.sqrt(np.mean(s[m].astype(np.float64) ** 2))) for s in (sx, sy))
    else:
        rmse = rms_s = (np.nan, np.nan)
    out["rmse_xy"], out["rms_sigma"] = rmse, rms_s
    out["calibration"] = tuple(r / s if s > 0 else np.nan for r, s in zip(rmse, rms_s))
    return out


def residual_noise(base, other, mask) -> float:
    """Grey-level residual of two images on one grid after a least-squares gain and offset.

    Parameters
    ----------
    base, other : numpy.ndarray
        ``(H, W)`` images, NaN as nodata (e.g. a base band and the registered band).
    mask : numpy.ndarray
        bool ``(H, W)``: pixels to use (e.g. the matched ones).

    Returns
    -------
    float
        Std of ``base - (g * other + o)`` over the finite pixels of ``mask``, in ``base``'s units.
    """
    import numpy as np

    m = np.asarray(mask, dtype=bool) & np.isfinite(base) & np.isfinite(other)
    if m.sum() < 3:
        raise ValueError("fewer than 3 pixels to measure the residual on")
    a = np.column_stack([other[m], np.ones(int(m.sum()))]).astype(np.float64)
    coef, *_ = np.linalg.lstsq(a, base[m].astype(np.float64), rcond=None)
    return float(np.std(base[m] - a @ coef))


def template_mean(a, size: tuple[int, int] = (7, 51)):
    """Mean of a field over a template window around every pixel, NaN as nodata.

    What a template of ``size`` (rows, columns; the dense matcher's default 51 x 7 is 7 rows
    by 51 columns) can recover of a field at best: structure inside the window is averaged.

    Parameters
    ----------
    a : numpy.ndarray
        ``(H, W)`` field, NaN where undefined.
    size : tuple of int
        Window (rows, columns).

    Returns
    -------
    numpy.ndarray
        float64 ``(H, W)``: the mean of the finite values in the window; NaN where ``a`` is.
    """
    import numpy as np
    import scipy.ndimage as ndi

    a = np.asarray(a, dtype=np.float64)
    valid = np.isfinite(a)
    num = ndi.uniform_filter(np.where(valid, a, 0.0), size, mode="nearest")
    den = ndi.uniform_filter(valid.astype(np.float64), size, mode="nearest")
    return np.where(valid, num / np.maximum(den, 1e-9), np.nan)


#: Hole lengths (px) of :func:`hole_check`: the post-filter fills up to its ``max_gap`` (24), the
#: line estimates take the longer ones.
HOLE_LENGTHS = (4, 8, 16, 24, 32, 64, 128)


def hole_check(ds, true_dx, true_dy, state: str, *, lengths=HOLE_LENGTHS, seed: int = 0, margin: int = 8,
               options=None, postfilter_options=None) -> list[dict]:
    """Seed 003 sec. 10's check of hole filling on a registered field.

    In every scan line at least 90 % matched, one stretch of ``length`` matches (with ``margin``
    matches on either side, at a random place) is removed; the field then goes through the
    post-filter (which fills holes up to its ``max_gap``) and the line step of
    :func:`geocoder.register` (:func:`geocoder.pipeline.lines.row_corrections` and
    :func:`~geocoder.pipeline.lines.line_field`, on a Dask client if one is current), and the
    values it gives the removed pixels are compared with the removed matches and the truth.

    Parameters
    ----------
    ds : xarray.Dataset
        A :func:`geocoder.register` output with dense matching and without the line step
        (``RegisterOptions(lines=LineOptions(enabled=False))``): the post-filtered field the line
        step starts from, whose matches are the raw ones and whose sigmas are theirs.
    true_dx, true_dy : numpy.ndarray
        The true field on the base grid.
    state : str
        A new Zarr store (local path) for the field the line step reads.
    lengths : sequence of int
    seed : int
        Seed of the stretches' places.
    margin : int
    options, postfilter_options : LineOptions, PostFilterOptions, optional
        Default: those of :class:`geocoder.RegisterOptions`.

    Returns
    -------
    list of dict
        Per length and way filled (``"filled"`` or ``"estimated"``, the status the line step
        gave a removed pixel): ``length``, ``by``, ``pixels``, ``rms_vs_match`` (px, against the
        removed matches), ``rmse`` (against the truth), ``over_1px`` (share off the truth by
        more than 1 px), ``calibration`` (RMSE / RMS(sigma) against the truth, x and y).
    """
    import json

    import dask
    import dask.array as da
    import numpy as np
    import zarr

    from geocoder.kernels.polynomial import PolyMap
    from geocoder.pipeline.lines import line_field, row_corrections
    from geocoder.pipeline.register import RegisterOptions
    from geocoder.pipeline.resample import poly_grid
    from geocoder.quality.postfilter import postfilter
    from geocoder.status import Status

    defaults = RegisterOptions()
    options = options or defaults.lines
    correlation = 2 * defaults.matching.alsc.radius + 1  # the template's length along the line, as register's
    postfilter_options = postfilter_options or defaults.postfilter
    st0 = np.asarray(ds.status.values)
    if (st0 == Status.ESTIMATED).any():
        raise ValueError("hole_check needs a field registered without the line step (LineOptions(enabled=False)); "
                         "this one has estimated pixels")
    dx0, dy0 = (np.asarray(ds[k].values, np.float64) for k in ("dx", "dy"))
    sx0, sy0, rho0 = (np.asarray(ds[k].values, np.float32) for k in ("sigma_x", "sigma_y", "correlation"))
    mapping = PolyMap.from_dict(json.loads(ds.attrs["mapping"]))
    h, w = st0.shape
    px, py = (poly_grid(mapping, (0, h), (0, w), k) for k in (0, 1))
    matched, inside = st0 == Status.MATCHED, st0 != Status.OUTSIDE
    good_rows = np.flatnonzero(matched.sum(axis=1) >= 0.9 * np.maximum(inside.sum(axis=1), 1))
    rng = np.random.default_rng(seed)
    chunk = ds.dx.data.chunks if hasattr(ds.dx.data, "chunks") else ((h,), (w,))
    tile = (chunk[0][0], chunk[1][0])
    out = []
    for length in lengths:
        removed = np.zeros((h, w), bool)
        for r in good_rows:
            fits = np.convolve(matched[r].astype(np.int32), np.ones(length + 2 * margin, np.int32),
                               mode="valid") == length + 2 * margin
            starts = np.flatnonzero(fits)
            if starts.size:
                c = int(rng.choice(starts)) + margin
                removed[r, c : c + length] = True
        keep = matched & ~removed
        status = np.where(keep, Status.MATCHED, np.where(inside, Status.NO_TEXTURE, Status.OUTSIDE)).astype(np.uint8)
        fdx, fdy, fst = postfilter(np.where(keep, dx0, np.nan), np.where(keep, dy0, np.nan), status,
                                   options=postfilter_options)
        good = (fst == Status.MATCHED) | (fst == Status.FILLED)
        sig = [np.where(fst == Status.MATCHED, s, np.nan).astype(np.float32) for s in (sx0, sy0)]
        stack = np.stack([fdx, fdy, fst, *sig, rho0]).astype(np.float32)
        store = f"{state}-{length}"
        zarr.open_group(store, mode="w", zarr_format=3).create_array("field", data=stack, chunks=(6, *tile))
        field = {"dx": da.from_array(np.where(good, fdx, px).astype(np.float32), chunks=tile),
                 "dy": da.from_array(np.where(good, fdy, py).astype(np.float32), chunks=tile),
                 "status": da.from_array(fst, chunks=tile),
                 "sigma_x": da.from_array(sig[0], chunks=tile), "sigma_y": da.from_array(sig[1], chunks=tile)}
        poly = tuple(da.from_array(p.astype(np.float32), chunks=tile) for p in (px, py))
        rows, line_fit = row_corrections(field, poly, options, correlation=correlation)
        chunks = field["dx"].chunks
        (res,) = dask.compute(line_field(store, chunks, mapping, rows, line_fit, options, correlation=correlation))
        for by, code in (("filled", Status.FILLED), ("estimated", Status.ESTIMATED)):
            m = removed & (res["status"] == code) & np.isfinite(true_dx) & np.isfinite(true_dy)
            if not m.any():
                out.append({"length": length, "by": by, "pixels": 0, "rms_vs_match": np.nan, "rmse": np.nan,
                            "over_1px": np.nan, "calibration": (np.nan, np.nan)})
                continue
            ex, ey = res["dx"][m] - true_dx[m], res["dy"][m] - true_dy[m]
            d_match = np.hypot(res["dx"][m] - dx0[m], res["dy"][m] - dy0[m])
            err = np.hypot(ex, ey)
            cal = tuple(float(np.sqrt(np.mean(e**2)) / np.sqrt(np.mean(res[s][m].astype(np.float64) ** 2)))
                        for e, s in ((ex, "sigma_x"), (ey, "sigma_y")))
            out.append({"length": length, "by": by, "pixels": int(m.sum()),
                        "rms_vs_match": float(np.sqrt(np.mean(d_match**2))), "rmse": float(np.sqrt(np.mean(err**2))),
                        "over_1px": float(np.mean(err > 1.0)), "calibration": cal})
    return out
