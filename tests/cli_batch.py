"""Run many ``geocoder`` command lines in one fresh process: ``python cli_batch.py < cases.json``.

A case is ``{"args": [...], "cwd": "..."}``. Each runs through the command line's own entry
point (:meth:`geocoder.cli._Main.main`, as ``python -m geocoder.cli`` does) with its own
stdout and stderr; an exception that escapes it is printed as the interpreter would print it,
with exit code 1. After each case the working directory is listed with the hash of every
file, so that the caller can tell what a case left behind. Prints one JSON list of
``{"code", "stdout", "stderr", "after"}``.

Starting the interpreter and importing geocoder's pipeline cost ~4 s of CPU per process on
the CI machine; the bad-input and data-loss tables of ``test_faults.py`` (42 cases) pay it once.
Tests call :func:`run_batch`.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import logging
import os
import subprocess
import sys
import traceback
from pathlib import Path


def snapshot(directory: str) -> dict[str, str]:
    """Every file and directory under ``directory`` (hidden ones included) with its content hash."""
    out = {}
    for root, dirs, files in os.walk(directory):
        for d in dirs:
            out[os.path.relpath(os.path.join(root, d), directory) + "/"] = "dir"
        for f in files:
            p = os.path.join(root, f)
            with open(p, "rb") as fh:
                out[os.path.relpath(p, directory)] = hashlib.sha256(fh.read()).hexdigest()
    return out


def run_case(args: list[str], cwd: str) -> dict:
    from geocoder.cli import main

    # a fresh logging set-up per case: the command's basicConfig binds the stderr of the moment
    for handler in logging.root.handlers[:]:
        logging.root.removeHandler(handler)
    out, err = io.StringIO(), io.StringIO()
    os.chdir(cwd)
    code = 0
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main.main(args, prog_name="geocoder")
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        except BaseException:  # noqa: BLE001 - what the interpreter would print for an uncaught exception
            traceback.print_exc()
            code = 1
    return {"code": code, "stdout": out.getvalue(), "stderr": err.getvalue(), "after": snapshot(cwd)}


def run_batch(cases: dict[str, list], cwd: Path, env: dict | None = None,
              timeout: float = 600) -> dict[str, tuple[subprocess.CompletedProcess, dict]]:
    """Every case's command line (name -> arguments after ``geocoder``) run in one fresh process,
    in order: by name, its result and the snapshot of ``cwd`` after it."""
    todo = [{"args": list(map(str, args)), "cwd": str(cwd)} for args in cases.values()]
    r = subprocess.run([sys.executable, __file__], input=json.dumps(todo), capture_output=True, text=True, env=env,
                       timeout=timeout)
    assert r.returncode == 0, r.stderr
    return {name: (subprocess.CompletedProcess(c["args"], res["code"], res["stdout"], res["stderr"]), res["after"])
            for name, c, res in zip(cases, todo, json.loads(r.stdout))}


if __name__ == "__main__":
    cases = json.load(sys.stdin)
    results = [run_case(c["args"], c["cwd"]) for c in cases]
    sys.stdout.write(json.dumps(results))
