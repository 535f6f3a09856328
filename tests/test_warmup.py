"""geocoder.warmup: after one warm-up, a fresh process finds every kernel the job runs in numba's cache."""

from __future__ import annotations

import json
import subprocess
import sys

# A fresh interpreter: runs the warm-up job, then lists every geocoder kernel it loaded or compiled.
PROBE = """
import json, sys
import numba
from geocoder.warmup import compile_kernels
compile_kernels()
hits, misses = {}, {}
for name, module in list(sys.modules.items()):
    if not name.startswith("geocoder"):
        continue
    for attr, obj in list(vars(module).items()):
        if isinstance(obj, numba.core.registry.CPUDispatcher) and obj.py_func.__module__ == name:
            key = f"{name}.{attr}"
            hits[key] = sum(obj.stats.cache_hits.values())
            misses[key] = sum(obj.stats.cache_misses.values())
print(json.dumps({"hits": hits, "misses": misses}))
"""


def test_a_fresh_process_loads_every_kernel_of_the_job_from_the_cache():
    # conftest's session start ran the same warm-up, so nothing the job needs may be compiled again
    r = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    found = json.loads(r.stdout.strip().splitlines()[-1])
    used = {k for k, n in found["hits"].items() if n} | {k for k, n in found["misses"].items() if n}
    # the dense job's main kernels are among them (the warm-up really ran the job)
    for kernel in ("geocoder.match.grow.grow", "geocoder.kernels.fieldlsq._solve_window",
                   "geocoder.kernels.interest._foerstner_kernel", "geocoder.quality.postfilter._postfilter_kernel"):
        assert kernel in used, f"{kernel} did not run in the warm-up"
    compiled = sorted(k for k, n in found["misses"].items() if n)
    assert not compiled, f"compiled again, not loaded from numba's cache: {compiled}"
