"""The worker environment has one source, :mod:`geocoder.runtime`; the files that must repeat it agree.

``workers/Dockerfile`` (``ENV``), ``workers/dask.yaml`` and the preload script cannot import
Python, so each is parsed (or run) here and compared with :data:`geocoder.runtime.WORKER_ENV`
and :data:`geocoder.runtime.WORKER_CONFIG`.
"""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

import yaml

from geocoder.runtime import WORKER_CONFIG, WORKER_ENV

WORKERS = Path(__file__).resolve().parents[1] / "workers"


def dockerfile_env(path: Path) -> dict[str, str]:
    """Variables set by the ``ENV KEY=VALUE ...`` instructions of a Dockerfile (later ones win)."""
    text = path.read_text().replace("\\\n", " ")
    env: dict[str, str] = {}
    for line in text.splitlines():
        op, _, rest = line.strip().partition(" ")
        if op.upper() != "ENV":
            continue
        for word in shlex.split(rest):
            key, sep, value = word.partition("=")
            assert sep, f"{path}: ENV {word!r} is not KEY=VALUE (the legacy 'ENV KEY VALUE' form is not used)"
            env[key] = value
    return env


def dotted(config: dict, key: str):
    """The value at a Dask-style dotted key of a nested mapping (KeyError naming the key if absent)."""
    node = config
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            raise KeyError(f"workers/dask.yaml has no {key!r}")
        node = node[part]
    return node


def test_dockerfile_sets_the_worker_env():
    env = dockerfile_env(WORKERS / "Dockerfile")
    assert {k: env.get(k) for k in WORKER_ENV} == WORKER_ENV


def test_dockerfile_parser_reads_continued_env_lines(tmp_path):
    f = tmp_path / "Dockerfile"
    f.write_text('FROM x\nENV A=1 \\\n    B="two words" \\\n    C=3\nRUN echo ENV D=4\nENV A=5\n')
    assert dockerfile_env(f) == {"A": "5", "B": "two words", "C": "3"}


def test_dask_yaml_holds_the_worker_config():
    config = yaml.safe_load((WORKERS / "dask.yaml").read_text())
    assert {k: dotted(config, k) for k in WORKER_CONFIG} == WORKER_CONFIG
    # the glibc setting reaches a worker through the nanny's environment, so both must agree
    env = dotted(config, "distributed.nanny.pre-spawn-environ")
    assert {k: v for k, v in env.items() if k in WORKER_ENV} == {k: WORKER_ENV[k] for k in env if k in WORKER_ENV}


def test_preload_sets_the_worker_env_in_a_clean_process():
    """Importing the preload (as ``dask worker --preload`` does) sets every variable not already set."""
    env = {k: v for k, v in os.environ.items() if k not in WORKER_ENV}
    env["GDAL_CACHEMAX"] = "64"  # set by the operator: the preload must keep it
    code = (
        "import importlib.util, json, os, sys\n"
        f"spec = importlib.util.spec_from_file_location('geocoder_preload', {str(WORKERS / 'geocoder_preload.py')!r})\n"
        "spec.loader.exec_module(importlib.util.module_from_spec(spec))\n"
        "import numba\n"
        f"seen = {{k: os.environ.get(k) for k in {sorted(WORKER_ENV)!r}}}\n"
        "print(json.dumps({'env': seen, 'numba_threads': numba.config.NUMBA_NUM_THREADS}))\n"
    )
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout.strip().splitlines()[-1])
    assert out["env"] == {**WORKER_ENV, "GDAL_CACHEMAX": "64"}
    assert out["numba_threads"] == int(WORKER_ENV["NUMBA_NUM_THREADS"]), "numba must see the pin it imported before"
