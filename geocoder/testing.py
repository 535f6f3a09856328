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
