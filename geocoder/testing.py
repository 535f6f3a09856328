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
