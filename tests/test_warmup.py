"""geocoder.warmup: after one warm-up, a fresh process finds every kernel the job runs in numba's cache,
and the parts compiled apart from the job are the very signatures the job uses."""

from __future__ import annotations

import json
import subprocess
import sys

# A fresh interpreter: runs the warm-up (its parts in this process, then the job), then lists every
# geocoder kernel it loaded or compiled, and how many signatures each holds.
PROBE = """
import json, sys
import numba
from geocoder.warmup import compile_kernels
compile_kernels(parallel=False)
hits, misses, signatures = {}, {}, {}
for name, module in list(sys.modules.items()):
    if not name.startswith("geocoder"):
        continue
    for attr, obj in list(vars(module).items()):
        if isinstance(obj, numba.core.registry.CPUDispatcher) and obj.py_func.__module__ == name:
            key = f"{name}.{attr}"
            hits[key] = sum(obj.stats.cache_hits.values())
            misses[key] = sum(obj.stats.cache_misses.values())
            signatures[key] = len(obj.signatures)
print(json.dumps({"hits": hits, "misses": misses, "signatures": signatures}))
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
    # the kernels compiled by the warm-up's own calls before the job (in a second process for the
    # growth) are the signatures the job runs: a second one would be compiled by the job itself
    for kernel in ("geocoder.match.grow.grow", "geocoder.kernels.fieldlsq._solve_window",
                   "geocoder.kernels.fieldlsq._accept", "geocoder.quality.postfilter._postfilter_kernel"):
        assert found["signatures"][kernel] == 1, f"{kernel}: the job used another signature than the warm-up's part"
