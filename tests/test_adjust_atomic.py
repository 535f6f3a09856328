"""The block adjustment's files are written whole: a failure mid-write leaves the previous ones.

The failure is real, not simulated: the writing process runs with a file-size limit
(``RLIMIT_FSIZE``, SIGXFSZ ignored), so the write that crosses it fails with ``EFBIG`` part-way
through the file, as on a full disk.  The same process without the limit succeeds and changes
the files, so the limit is what made it fail.
"""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from geocoder.adjust.io import read_frames, read_points, scanner_to_dict, write_observations, write_points
from geocoder.simulate.adjust_experiments import block_setup, collinearity_frame
from geocoder.simulate.points import GroundPoints


def _act(what: str, folder: str) -> None:
    """One write of the adjustment's files into ``folder`` (also what the limited child runs)."""
    from geocoder.adjust import io
    from geocoder.adjust.run import adjust_files

    p = lambda name: os.path.join(folder, name)  # noqa: E731
    if what == "points":
        pts = io.read_points(p("points.csv"))
        io.write_points(p("points.csv"), pts, pts.xyz + 1.0)
    elif what == "frames":
        frames, specs = io.read_frames(p("frames.json"))
        io.write_frames(p("frames.json"), specs, [f.params + 1e-9 for f in frames])
    else:  # a rerun of the adjustment with the control points moved by 1 m
        adjust_files(p("frames.json"), p("moved.csv"), p("obs.csv"), p("out"), overwrite=True)


#: The child: a file-size limit (bytes), then :func:`_act`; prints the errno it failed with.
_CHILD = r"""
import json, resource, signal, sys
sys.path.insert(0, sys.argv[4])
from test_adjust_atomic import _act

signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[3]), resource.RLIM_INFINITY))
try:
    _act(sys.argv[1], sys.argv[2])
except OSError as exc:
    print(json.dumps({"errno": exc.errno}))
    sys.exit(3)
print(json.dumps({"errno": 0}))
"""


def _limited(what: str, folder, limit: int) -> int:
    """Run :func:`_act` in a child whose files may not grow beyond ``limit`` bytes; its errno (0 = ok)."""
    r = subprocess.run([sys.executable, "-c", _CHILD, what, str(folder), str(limit), os.path.dirname(__file__)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode in (0, 3), r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])["errno"]


def _snapshot(folder) -> dict[str, bytes]:
    out = {}
    for root, _, files in os.walk(folder):
        for name in files:
            path = os.path.join(root, name)
            with open(path, "rb") as f:
                out[os.path.relpath(path, folder)] = f.read()
    return out


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A 2-frame block of the simulator as the three input files of ``geocoder adjust``."""
    folder = tmp_path_factory.mktemp("atomic")
    truths, grid, check, ties, obs = block_setup(size=0.2, strips=2, frames=1, tie_per_overlap=4)
    pts = GroundPoints.concatenate([grid, check])
    write_points(folder / "points.csv", pts)
    write_observations(folder / "obs.csv", obs.subset(np.isin(obs.point, pts.id)))
    frames = []
    for t in truths:
        f = collinearity_frame(t, reduced=True)
        frames.append({"model": "linescanner", "scanner": scanner_to_dict(f.model.template),
                       "free": f.model.free.tolist(), "prior_sigma": (1 / np.sqrt(np.diag(f.prior_weight))).tolist()})
    (folder / "frames.json").write_text(json.dumps({"frames": frames}))
    return folder


@pytest.mark.parametrize("what,name", [("points", "points.csv"), ("frames", "frames.json")])
def test_a_writer_that_fails_mid_write_leaves_the_previous_file(inputs, tmp_path, what, name):
    for n in ("points.csv", "obs.csv", "frames.json"):
        (tmp_path / n).write_bytes((inputs / n).read_bytes())
    before = (tmp_path / name).read_bytes()
    assert len(before) > 1000
    # the new file is at least as long as the old one: a limit of half of it fails mid-write
    assert _limited(what, tmp_path, len(before) // 2) == errno.EFBIG
    assert (tmp_path / name).read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["frames.json", "obs.csv", "points.csv"]  # no partial file left
    # without the limit the same write succeeds and replaces the file
    _act(what, str(tmp_path))
    after = (tmp_path / name).read_bytes()
    assert after != before
    assert sorted(os.listdir(tmp_path)) == ["frames.json", "obs.csv", "points.csv"]
    if what == "points":
        np.testing.assert_allclose(read_points(str(tmp_path / name)).xyz,
                                   read_points(str(inputs / name)).xyz + 1.0, atol=1e-4)
    else:
        frames, _ = read_frames(str(tmp_path / name))
        assert len(frames) == 2 and all(np.all(f.params != 0) for f in frames)


def test_adjust_files_failing_mid_write_leaves_the_previous_output(inputs, tmp_path):
    for n in ("points.csv", "obs.csv", "frames.json"):
        (tmp_path / n).write_bytes((inputs / n).read_bytes())
    pts = read_points(str(tmp_path / "points.csv"))
    write_points(tmp_path / "moved.csv", pts, pts.xyz + 1.0)
    from geocoder.adjust.run import adjust_files

    first = adjust_files(str(tmp_path / "frames.json"), str(tmp_path / "points.csv"), str(tmp_path / "obs.csv"),
                         str(tmp_path / "out"))
    assert first["converged"] and first["check_points"] > 0
    before = _snapshot(tmp_path / "out")
    assert {"frames.json", "points.csv", "residuals.csv", "report.md", "summary.json"} <= set(before)
    # a limit below the largest output: the rerun fails part-way through writing its files
    limit = max(len(v) for v in before.values()) // 2
    assert _limited("adjust", tmp_path, limit) == errno.EFBIG
    assert _snapshot(tmp_path / "out") == before
    assert not [n for n in os.listdir(tmp_path) if n.startswith(".")]  # the partial output was removed
    # without the limit the rerun replaces it
    _act("adjust", str(tmp_path))
    after = _snapshot(tmp_path / "out")
    assert set(after) == set(before) and after["points.csv"] != before["points.csv"]
    assert not [n for n in os.listdir(tmp_path) if n.startswith(".")]
