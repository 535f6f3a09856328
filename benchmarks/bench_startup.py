"""Start-up of a fresh process: ``import geocoder``, the command line's help and a usage error.

Every ``geocoder`` command, every Dask worker process and every CLI call of the test suite
starts a Python process that imports geocoder; a usage error or ``--help`` should answer at
once, not after loading the pipeline, its numba kernels and their libraries. Each row is the
median wall time of ``--repeat`` fresh processes (alternating between the trees, so both
see the same machine), and the number of modules the process had loaded.

Usage::

    python benchmarks/bench_startup.py [--before-rev 3057256] [--repeat 7]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: What each row runs in a fresh interpreter (after the statement: print the modules loaded).
CASES = {
    "import geocoder": "import geocoder",
    "geocoder --help": "import sys; sys.argv = ['geocoder', '--help']; import geocoder.cli as c; c.main()",
    "usage error (register --tile 0)": ("import sys; sys.argv = ['geocoder', 'register', 'a.tif', 'b.tif', '--out', 'o.zarr', "
                                         "'--tile', '0']; import geocoder.cli as c; c.main()"),
    "import geocoder + geocoder.register": "import geocoder; geocoder.register",
}


def run_case(code: str, pythonpath: str | None) -> tuple[float, int]:
    """Wall seconds of a fresh interpreter running ``code``, and how many modules it loaded."""
    env = dict(os.environ)
    if pythonpath:
        env["PYTHONPATH"] = pythonpath + os.pathsep + env.get("PYTHONPATH", "")
    report = "import atexit, sys, json; atexit.register(lambda: sys.__stderr__.write('MODULES ' + json.dumps(len(sys.modules)) + chr(10)))"
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", f"{report}\n{code}"], env=env, capture_output=True, text=True, cwd=tempfile.gettempdir())
    wall = time.perf_counter() - t
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("MODULES ")]
    if not lines:
        raise RuntimeError(f"{code!r} failed: {r.stderr[-2000:]}")
    return wall, json.loads(lines[-1].split(" ", 1)[1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before-rev", default=None, help="also run this git revision's code")
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-startup-") as tmp:
        trees: list[tuple[str, str | None]] = [("now", None)]
        if args.before_rev:
            before = Path(tmp) / "before-src"
            before.mkdir()
            archive = subprocess.run(["git", "-C", str(ROOT), "archive", args.before_rev], check=True, capture_output=True).stdout
            subprocess.run(["tar", "-x", "-C", str(before)], input=archive, check=True)
            trees.insert(0, (f"before ({args.before_rev})", str(before)))
        for _, path in trees:  # warm the disk cache and numba's index before timing
            run_case(CASES["import geocoder + geocoder.register"], path)
        times: dict[tuple[str, str], list[float]] = {}
        modules: dict[tuple[str, str], int] = {}
        for _ in range(args.repeat):
            for case, code in CASES.items():
                for label, path in trees:
                    wall, n = run_case(code, path)
                    times.setdefault((label, case), []).append(wall)
                    modules[(label, case)] = n
    print(f"\nStart-up of a fresh process: median of {args.repeat} (python {sys.version.split()[0]}, {os.cpu_count()} CPUs)\n")
    print("| | " + " | ".join(label for label, _ in trees) + " |")
    print("|---|" + "---:|" * len(trees))
    for case in CASES:
        cells = [f"{statistics.median(times[(label, case)]):.2f} s ({modules[(label, case)]} modules)" for label, _ in trees]
        print(f"| {case} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
