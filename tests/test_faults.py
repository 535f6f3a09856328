"""Bad inputs and faults, through the real command line: exit code, one line, what is left on disk.

Every case runs ``geocoder`` as a subprocess (the test cluster's scheduler where a job gets as
far as computing; the data-loss and bad-input tables each in one process of their own, case
after case, see :mod:`cli_batch`: a fresh process per case cost ~4 s of CPU for the imports)
and asserts the exit code (2 bad input or usage, 3 environment, 130 interrupted), the single
``geocoder: error: ...`` line naming the file or resource, that no traceback is printed, and
that nothing the user had was deleted, changed or hidden. The data-loss cases come first.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rasterio
from cli_batch import run_batch, snapshot

from geocoder.scene import write_geotiff
from geocoder.simulate.texture import synthetic_ortho
from geocoder.simulate.warp import make_pair

pytestmark = pytest.mark.cluster

GEOCODER = [sys.executable, "-m", "geocoder.cli", "-q"]


def run(*args, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([*GEOCODER, *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=timeout)


def assert_error(r: subprocess.CompletedProcess, code: int, *needles: str) -> str:
    """One ``geocoder: error:`` line, last on stderr, holding every needle; no traceback."""
    assert r.returncode == code, (r.returncode, r.stderr)
    assert "Traceback" not in r.stderr, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("geocoder: error: ")]
    assert len(lines) == 1, r.stderr
    assert r.stderr.strip().splitlines()[-1] == lines[0]
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    """A working directory with the inputs of every case (and a user's own files)."""
    d = tmp_path_factory.mktemp("faults")
    src = synthetic_ortho((352, 352), seed=5)
    pair = make_pair(src, shape=(256, 256), seed=5, margin=48)
    write_geotiff(d / "base.tif", pair.base)
    write_geotiff(d / "dist.tif", pair.distorted)
    write_geotiff(d / "tiny1.tif", np.ones((1, 1), np.float32))
    write_geotiff(d / "tiny3.tif", np.arange(9, dtype=np.float32).reshape(3, 3))
    write_geotiff(d / "constant.tif", np.full((256, 256), 7.0, np.float32))
    write_geotiff(d / "allnan.tif", np.full((256, 256), np.nan, np.float32))
    with rasterio.open(d / "nodata.tif", "w", driver="GTiff", width=256, height=256, count=1, dtype="uint8", nodata=0) as f:
        f.write(np.zeros((256, 256), np.uint8), 1)
    with rasterio.open(d / "complex.tif", "w", driver="GTiff", width=64, height=64, count=1, dtype="complex64") as f:
        f.write(np.ones((64, 64), np.complex64), 1)
    with rasterio.open(d / "whole.tif", "w", driver="GTiff", width=512, height=512, count=1, dtype="float32") as f:
        f.write(np.squeeze(synthetic_ortho((512, 512), seed=6)).astype(np.float32), 1)
    data = (d / "whole.tif").read_bytes()
    (d / "truncated.tif").write_bytes(data[: len(data) // 2])
    (d / "whole.tif").unlink()
    (d / "notes.tif").write_text("not a raster\n")
    (d / "mine").mkdir()
    (d / "mine" / "thesis.txt").write_text("years of work\n")
    (d / "report.txt").write_text("a user's file\n")
    return d


# --- data loss: nothing the user has is ever deleted, replaced or hidden ----------------------

DATA_LOSS = {
    "out is a user's directory": (["register", "base.tif", "dist.tif", "--out", "mine"], 2, ["mine", "geocoder did not write"]),
    "out is a user's directory, --overwrite": (["register", "base.tif", "dist.tif", "--out", "mine", "--overwrite"], 2,
                                               ["geocoder did not write"]),
    "out is the working directory": (["register", "base.tif", "dist.tif", "--out", "."], 2, ["working directory"]),
    "out is empty": (["register", "base.tif", "dist.tif", "--out", ""], 2, ["--out: the output path is empty"]),
    "out contains the working directory": (["register", "base.tif", "dist.tif", "--out", ".."], 2, ["working directory"]),
    "out is the base image": (["register", "base.tif", "dist.tif", "--out", "base.tif"], 2, ["base.tif", "an input"]),
    "out is the distorted image, --overwrite": (["register", "base.tif", "dist.tif", "--out", "dist.tif", "--overwrite"], 2,
                                                ["dist.tif", "an input"]),
    "out is a user's file": (["register", "base.tif", "dist.tif", "--out", "report.txt"], 2, ["report.txt", "a file geocoder did not write"]),
    "out in a missing directory": (["register", "base.tif", "dist.tif", "--out", "nowhere/o.zarr"], 2, ["parent directory does not exist"]),
    "ingest into a user's directory": (["ingest", "base.tif", "mine"], 2, ["mine", "geocoder did not write"]),
    "ingest into the working directory": (["ingest", "base.tif", "."], 2, ["working directory"]),
    "ingest onto its input": (["ingest", "base.tif", "base.tif", "--overwrite"], 2, ["an input"]),
    "simulate into a user's directory": (["simulate", "airborne", "--ortho", "synthetic", "--out", "mine"], 2, ["geocoder did not write"]),
    "demo into a user's directory": (["demo", "--out", "mine"], 2, ["mine", "geocoder did not write"]),
    "demo into the working directory": (["demo", "--out", "."], 2, ["working directory"]),
}


@pytest.fixture(scope="module")
def data_loss_runs(work):
    before = snapshot(work)
    return before, run_batch({name: ["-q", *args] for name, (args, _, _) in DATA_LOSS.items()}, work)


@pytest.mark.parametrize("case", list(DATA_LOSS))
def test_data_loss_refused(data_loss_runs, case):
    _, code, needles = DATA_LOSS[case]
    before, runs = data_loss_runs
    r, after = runs[case]
    assert_error(r, code, *needles)
    assert after == before  # nothing deleted, changed, hidden or left behind


def test_out_dot_in_an_empty_working_directory_keeps_the_directory(work, tmp_path, client):
    """``--out .`` from a fresh directory: refused before anything is written (the case that emptied it)."""
    (tmp_path / "keep.txt").write_text("x")
    r = run("register", work / "base.tif", work / "dist.tif", "--out", ".", "--scheduler", client.scheduler.address, cwd=tmp_path)
    assert_error(r, 2, "working directory")
    assert sorted(os.listdir(tmp_path)) == ["keep.txt"]


def test_overwrite_replaces_only_geocoder_outputs(work, tmp_path, client):
    out = tmp_path / "o.zarr"
    args = ["-q", "register", work / "base.tif", work / "dist.tif", "--out", out, "--no-dense", "--tile", 128,
            "--scheduler", client.scheduler.address]
    # the three command lines in one process, one after the other (see cli_batch)
    runs = run_batch({"first": args, "again": args, "overwrite": [*args, "--overwrite"]}, tmp_path)
    (first, after_first), (again, after_again), (overwrite, _) = runs.values()
    assert first.returncode == 0, first.stderr
    assert "o.zarr/zarr.json" in after_first
    assert_error(again, 2, str(out), "pass --overwrite")
    assert after_again == after_first  # refused: the first output untouched
    assert overwrite.returncode == 0, overwrite.stderr
    assert json.loads((out / "zarr.json").read_text())["attributes"]["geocoder_product"] == "register"
    assert sorted(os.listdir(tmp_path)) == ["o.zarr"]  # no old store, job directory or lock left
    # an input inside an output geocoder wrote: replacing that output would delete the input
    (out / "inner.tif").write_bytes((work / "base.tif").read_bytes())
    runs = run_batch({"inner": ["-q", "register", out / "inner.tif", work / "dist.tif", "--out", out, "--overwrite"],
                      "nested": ["-q", "register", out, work / "dist.tif", "--out", out / "nested.zarr"]}, tmp_path)
    assert_error(runs["inner"][0], 2, "contains the input")
    # an output inside an input store
    assert_error(runs["nested"][0], 2, "lies inside the input")


def test_demo_reruns_into_its_own_directory_only(tmp_path, client):
    sched = ["--scheduler", client.scheduler.address]
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "data.csv").write_text("1,2\n")
    demo = ["-q", "demo", "--size", 256, "--tile", 128, "--out", "d", *sched]
    # the three command lines in one process, one after the other (see cli_batch)
    runs = run_batch({"first": demo, "again": demo, "other": ["-q", "demo", "--out", "other", *sched]}, tmp_path)
    (first, after_first), (again, _), (other, after_other) = runs.values()
    assert first.returncode == 0, first.stderr
    assert "d/registered.zarr/zarr.json" in after_first
    assert again.returncode == 0, again.stderr  # its own directory: run again in place
    assert_error(other, 2, "geocoder did not write")
    assert sorted(k for k in after_other if k.startswith("other")) == ["other/", "other/data.csv"]
    assert (tmp_path / "other" / "data.csv").read_text() == "1,2\n"


# --- bad input: one line naming the file, no job directory left ------------------------------

BAD_INPUT = {
    "missing base": (["register", "nope.tif", "dist.tif"], ["nope.tif: no such file"]),
    "1 x 1 image": (["register", "tiny1.tif", "dist.tif"], ["tiny1.tif", "is 1 x 1 px"]),
    "3 x 3 image": (["register", "base.tif", "tiny3.tif"], ["tiny3.tif", "is 3 x 3 px"]),
    "constant image": (["register", "constant.tif", "dist.tif"], ["constant.tif", "is constant"]),
    "all-NaN image": (["register", "base.tif", "allnan.tif"], ["allnan.tif", "no valid pixels"]),
    "all-nodata image": (["register", "nodata.tif", "dist.tif"], ["nodata.tif", "no valid pixels"]),
    "truncated GeoTIFF": (["register", "truncated.tif", "dist.tif"], ["truncated.tif", "truncated or damaged"]),
    "complex pixels": (["register", "complex.tif", "dist.tif"], ["complex.tif", "complex pixels"]),
    "not a raster": (["register", "notes.tif", "dist.tif"], ["notes.tif", "cannot be read as a raster"]),
    "band that does not exist": (["register", "base.tif", "dist.tif", "--band", 5], ["band 5 does not exist"]),
    "band 0": (["register", "base.tif", "dist.tif", "--band", 0], ["--band", "0 is not in the range"]),
    "tile not a multiple of 64": (["register", "base.tif", "dist.tif", "--tile", 100], ["multiple of 64"]),
    "tile 0": (["register", "base.tif", "dist.tif", "--tile", 0], ["--tile", "0 is not in the range"]),
    "order 7": (["register", "base.tif", "dist.tif", "--order", 7], ["--order"]),
    "unknown resampling": (["register", "base.tif", "dist.tif", "--resampling", "magic"], ["--resampling", "magic"]),
    "unknown option": (["register", "base.tif", "dist.tif", "--fast"], ["No such option", "--fast"]),
    "unparsable scheduler address": (["register", "base.tif", "dist.tif", "--scheduler", "nonsense::addr"],
                                     ["nonsense::addr", "not a usable Dask scheduler address"]),
    "TLS scheduler without certificates": (["register", "base.tif", "dist.tif", "--scheduler", "tls://127.0.0.1:1"],
                                           ["tls://127.0.0.1:1", "TLS needs certificates"]),
    "ingest --tile 0": (["ingest", "base.tif", "x.zarr", "--tile", 0], ["--tile", "0 is not in the range"]),
    "ingest --tile -1": (["ingest", "base.tif", "x.zarr", "--tile", -1], ["--tile", "-1 is not in the range"]),
    "ingest a truncated GeoTIFF": (["ingest", "truncated.tif", "x.zarr"], ["truncated.tif", "truncated or damaged"]),
    "ingest a missing file": (["ingest", "nope.tif", "x.zarr"], ["nope.tif: no such file"]),
    "simulate --noise -1": (["simulate", "airborne", "--ortho", "synthetic", "--out", "s.zarr", "--noise", -1], ["--noise"]),
    "simulate --pixel 0": (["simulate", "satellite", "--ortho", "synthetic", "--out", "s.zarr", "--pixel", 0], ["--pixel"]),
    "simulate a missing ortho": (["simulate", "airborne", "--ortho", "nope.tif", "--out", "s.zarr"], ["nope.tif: no such file"]),
    "demo --size 10": (["demo", "--size", 10, "--out", "d"], ["--size"]),
    "cluster up --port 70000": (["cluster", "up", "--port", 70000, "--dir", "c"], ["--port"]),
}


UNREACHABLE = "unreachable scheduler"


@pytest.fixture(scope="module")
def bad_input_runs(work, client, data_loss_runs):  # after the data-loss cases, as in the file
    def full(args: list) -> list:
        if args[0] == "register":
            args = [*args, "--out", "o.zarr", "--tile", 128] if "--tile" not in args else [*args, "--out", "o.zarr"]
            if "--scheduler" not in args:
                args += ["--scheduler", client.scheduler.address]
        elif args[0] == "ingest":
            args = [*args, "--scheduler", client.scheduler.address]
        return args

    before = snapshot(work)
    cases = {name: ["-q", *full(args)] for name, (args, _) in BAD_INPUT.items()}
    # the environment failure below, in the same process (one interpreter start less)
    cases[UNREACHABLE] = ["-q", "register", "base.tif", "dist.tif", "--out", "o.zarr", "--scheduler", "tcp://127.0.0.1:1"]
    return before, run_batch(cases, work)


@pytest.mark.parametrize("case", list(BAD_INPUT))
def test_bad_input_is_one_line(bad_input_runs, case):
    _, needles = BAD_INPUT[case]
    before, runs = bad_input_runs
    r, after = runs[case]
    assert_error(r, 2, *needles)
    assert after == before  # no output, no job directory, no lock


# --- environment failures: exit 3, the job kept for a rerun ----------------------------------

def test_unreachable_scheduler_is_reported_with_its_connect_timeout(bad_input_runs):
    """``register base.tif dist.tif --out o.zarr --scheduler tcp://127.0.0.1:1`` in ``work``
    (run in the bad-input table's process, after its cases)."""
    before, runs = bad_input_runs
    r, after = runs[UNREACHABLE]
    # the message states the client's own 10 s connect timeout (was Dask's 60 s); no clock is read here
    assert_error(r, 3, "tcp://127.0.0.1:1", "does not answer", "after 10 s")
    assert after == before


def test_a_second_job_to_the_same_output_is_refused(work, tmp_path, client):
    """A live holder of the lock (this test process stands in for the first job) refuses the second."""
    import psutil

    job = tmp_path / ".o.zarr.geocoder-job"
    job.mkdir()
    lock = {"host": os.uname().nodename, "pid": os.getpid(), "process_start": psutil.Process().create_time(), "since": time.time()}
    (job / "lock.json").write_text(json.dumps(lock))
    before = snapshot(tmp_path)
    r = run("register", work / "base.tif", work / "dist.tif", "--out", "o.zarr", "--tile", 128,
            "--scheduler", client.scheduler.address, cwd=tmp_path)
    assert_error(r, 3, "o.zarr", "another geocoder job is writing it", f"pid {os.getpid()}")
    assert snapshot(tmp_path) == before  # the other job's directory and lock untouched
    # the holder died (a pid that no longer runs): the lock is taken over and the job runs
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    lock.update(pid=dead.pid, process_start=0.0)
    (job / "lock.json").write_text(json.dumps(lock))
    r = run("register", work / "base.tif", work / "dist.tif", "--out", "o.zarr", "--tile", 128, "--no-dense",
            "--scheduler", client.scheduler.address, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert sorted(os.listdir(tmp_path)) == ["o.zarr"]


def test_two_jobs_started_together_one_runs_one_is_refused(work, tmp_path, client):
    args = [*GEOCODER, "register", work / "base.tif", work / "dist.tif", "--out", "o.zarr", "--tile", 128,
            "--scheduler", client.scheduler.address]
    procs = [subprocess.Popen(list(map(str, args)), cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    results = [p.communicate(timeout=300) + (p.returncode,) for p in procs]
    codes = sorted(rc for _, _, rc in results)
    assert codes in ([0, 3], [0, 0]), results  # [0, 0]: the second started after the first had finished
    for out, err, rc in results:
        assert "Traceback" not in err
        if rc == 3:
            assert "another geocoder job is writing it" in err.strip().splitlines()[-1]
    assert sorted(os.listdir(tmp_path)) == ["o.zarr"]


def test_disk_full_keeps_the_job_for_a_rerun(work, tmp_path, client):
    small = tmp_path / "small"
    small.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=400k", "tmpfs", str(small)], capture_output=True).returncode:
        pytest.skip("cannot mount a small tmpfs here (needs root)")
    try:
        r = run("register", work / "base.tif", work / "dist.tif", "--out", small / "o.zarr", "--tile", 128,
                "--scheduler", client.scheduler.address, cwd=tmp_path)
        line = assert_error(r, 3, "No space left on device", "run the same command again")
        assert str(small) in line
        assert os.listdir(small) == [".o.zarr.geocoder-job"]  # kept, unlocked, for the rerun
        assert not (small / ".o.zarr.geocoder-job" / "lock.json").exists()
    finally:
        subprocess.run(["umount", str(small)], check=True)


def wait_past_correspondence(p: subprocess.Popen, job: Path, timeout: float = 240) -> None:
    """Until the running job's manifest records a correspondence stage (dense matching follows)."""
    manifest = job / "manifest.json"
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and p.poll() is None:
        if manifest.exists() and "correspondence" in manifest.read_text():
            break
        time.sleep(0.2)
    assert p.poll() is None, p.communicate()


def test_ctrl_c_is_one_line_and_the_rerun_resumes(tmp_path, client):
    """SIGINT to the whole process group, as a terminal's Ctrl-C, mid dense matching."""
    src = synthetic_ortho((608, 608), seed=8)
    pair = make_pair(src, shape=(512, 512), seed=8, margin=48)
    write_geotiff(tmp_path / "b.tif", pair.base)
    write_geotiff(tmp_path / "d.tif", pair.distorted)
    # a terminal's job starts with Ctrl-C at its default; a test runner started in the
    # background of a non-interactive shell would hand SIGINT down ignored
    default_sigint = ("import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
                      "sys.argv[0] = 'geocoder'; runpy.run_module('geocoder.cli', run_name='__main__')")
    args = [sys.executable, "-c", default_sigint, "register", "b.tif", "d.tif", "--out", "o.zarr", "--tile", 128]  # a local cluster of its own
    p = subprocess.Popen(list(map(str, args)), cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    wait_past_correspondence(p, tmp_path / ".o.zarr.geocoder-job")
    os.killpg(p.pid, signal.SIGINT)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert err.strip().splitlines()[-1].startswith("geocoder: error: interrupted")
    assert not (tmp_path / "o.zarr").exists()
    assert (tmp_path / ".o.zarr.geocoder-job").is_dir()
    r = run("register", "b.tif", "d.tif", "--out", "o.zarr", "--tile", 128, "--scheduler", client.scheduler.address, cwd=tmp_path)
    # another scheduler, same job: the finished stages are reused
    assert r.returncode == 0, r.stderr
    assert "resumed:" in r.stdout
    assert sorted(os.listdir(tmp_path)) == ["b.tif", "d.tif", "o.zarr"]


def test_ctrl_c_dropped_by_a_garbage_collector_callback_still_stops_the_job(tmp_path):
    """Python delivers Ctrl-C as a KeyboardInterrupt in whatever the main thread runs; inside a
    garbage collector callback or a finalizer it is printed as "Exception ignored" and dropped.
    The Ctrl-C test above once ended so (the interrupt fell into distributed's GC callback, the job
    ran to its end and exited 0). Here the interrupt is raised in such a callback on purpose."""
    src = synthetic_ortho((608, 608), seed=8)
    pair = make_pair(src, shape=(512, 512), seed=8, margin=48)
    write_geotiff(tmp_path / "b.tif", pair.base)
    write_geotiff(tmp_path / "d.tif", pair.distorted)
    trigger = tmp_path / "interrupt-now"
    script = (
        "import gc, os, runpy, sys, threading\n"
        "def callback(phase, info):\n"
        f"    if threading.current_thread() is threading.main_thread() and os.path.exists({str(trigger)!r}):\n"
        f"        os.remove({str(trigger)!r})\n"
        "        raise KeyboardInterrupt\n"
        "gc.callbacks.append(callback)\n"
        "sys.argv[0] = 'geocoder'\n"
        "runpy.run_module('geocoder.cli', run_name='__main__')\n"
    )
    args = [sys.executable, "-c", script, "register", "b.tif", "d.tif", "--out", "o.zarr", "--tile", 128]
    p = subprocess.Popen(list(map(str, args)), cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    wait_past_correspondence(p, tmp_path / ".o.zarr.geocoder-job")
    trigger.touch()
    _, err = p.communicate(timeout=240)
    assert not trigger.exists(), "the main thread ran no garbage collection before the job ended"
    assert p.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err and "Exception ignored" not in err, err
    assert err.strip().splitlines()[-1].startswith("geocoder: error: interrupted")
    assert not (tmp_path / "o.zarr").exists()
    assert (tmp_path / ".o.zarr.geocoder-job").is_dir()


def test_a_busy_zarr_thread_at_the_end_of_a_command_prints_no_traceback():
    # the Ctrl-C test above once failed on a loaded machine: zarr's exit handler waited 0.2 s for
    # its I/O thread, closed the still running loop and Python printed "Cannot close a running event
    # loop" with a traceback after geocoder's one line. Here the thread is kept busy for 1 s as a
    # command ends (deterministically, any machine); the CLI now lets it stop first
    script = (
        "import time, zarr, zarr.core.sync as s\n"
        "from geocoder.cli import main\n"
        "zarr.open_group(zarr.storage.MemoryStore(), mode='w').create_array('a', shape=(4,), dtype='f4')\n"
        "s.loop[0].call_soon_threadsafe(time.sleep, 1.0)\n"
        "time.sleep(0.05)\n"
        "main(['--version'])\n"
    )
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and "version" in p.stdout
    assert p.stderr == "", p.stderr


def test_identical_images_have_no_outside_pixels(work, tmp_path, client):
    """Round-off of an identity fit (1e-5 px) must not leave the first row and column 'outside'."""
    from geocoder import Status, register

    ds = register(work / "base.tif", work / "base.tif", tile=128, client=client, dense=False)
    assert int((ds.status.values == Status.OUTSIDE).sum()) == 0
    assert np.isfinite(ds.registered.values).all()


def test_options_are_honoured(work, client):
    """``options=`` was silently overwritten by the keywords' defaults (order 3 ran as 2, dense=False as dense)."""
    from geocoder import RegisterOptions, Status, register

    ds = register(work / "base.tif", work / "dist.tif", client=client, options=RegisterOptions(order=3, dense=False, tile=128))
    assert json.loads(ds.attrs["mapping"])["order"] == 3
    assert set(np.unique(ds.status.values)) <= {Status.MODEL, Status.OUTSIDE}
    # a keyword given explicitly still wins
    ds = register(work / "base.tif", work / "dist.tif", client=client, order=1, options=RegisterOptions(order=3, dense=False, tile=128))
    assert json.loads(ds.attrs["mapping"])["order"] == 1


def test_scheduler_lost_mid_job_keeps_the_job(tmp_path):
    """The scheduler of a 'cluster up' cluster killed mid dense matching: exit 3, one line, job kept."""
    src = synthetic_ortho((608, 608), seed=9)
    pair = make_pair(src, shape=(512, 512), seed=9, margin=48)
    write_geotiff(tmp_path / "b.tif", pair.base)
    write_geotiff(tmp_path / "d.tif", pair.distorted)
    up = run("cluster", "up", "--workers", 1, "--dir", tmp_path / "cl", cwd=tmp_path, timeout=180)
    assert up.returncode == 0, up.stderr
    info = json.loads((tmp_path / "cl" / "cluster.json").read_text())
    try:
        p = subprocess.Popen([*GEOCODER, "register", "b.tif", "d.tif", "--out", "o.zarr", "--tile", "128", "--scheduler",
                              str(tmp_path / "cl" / "cluster.json")], cwd=tmp_path, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
        wait_past_correspondence(p, tmp_path / ".o.zarr.geocoder-job")
        os.kill(info["scheduler_pid"], signal.SIGKILL)
        _, err = p.communicate(timeout=180)
    finally:
        down = run("cluster", "down", "--dir", tmp_path / "cl", cwd=tmp_path, timeout=180)
    r = subprocess.CompletedProcess(p.args, p.returncode, "", err)
    assert_error(r, 3, info["address"], "lost the Dask scheduler", "run the same command again")
    assert (tmp_path / ".o.zarr.geocoder-job" / "manifest.json").exists()
    assert not (tmp_path / ".o.zarr.geocoder-job" / "lock.json").exists() and not (tmp_path / "o.zarr").exists()
    assert down.returncode == 0 and "had already stopped" in down.stdout


def test_lost_scheduler_forms_are_cluster_failures():
    """Each way distributed reports a lost scheduler mid-call is told apart from a bug.

    ``ConnectionPool is closed`` is what a call to the scheduler (e.g. ``Client.nthreads``)
    raises once the client has given up on it: seen when the scheduler was killed mid
    correspondence (test above), where it came out as a traceback.
    """
    from distributed.client import ClosedClientError
    from distributed.comm.core import CommClosedError

    from geocoder.runtime import is_cluster_failure

    assert is_cluster_failure(CommClosedError("in <TCP ...>: Stream is closed"))
    assert is_cluster_failure(RuntimeError("ConnectionPool is closed"))
    # the client closed itself on losing the scheduler (a CI run: the next call on it raised this)
    assert is_cluster_failure(ClosedClientError("Client is closed. Can't send cancel-keys message."))
    assert is_cluster_failure(OSError("Timed out trying to connect to tcp://127.0.0.1:1 after 30 s"))
    assert not is_cluster_failure(RuntimeError("some other runtime error"))
    assert not is_cluster_failure(ValueError("ConnectionPool is closed"))
