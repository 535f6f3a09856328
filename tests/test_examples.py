"""The example notebook (examples/register_pair.py), run as a real program and read as a notebook."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK = ROOT / "examples" / "register_pair.py"
FIGURES = ("displacement", "sigma_status", "before_after")
RMSE = re.compile(r"RMSE against truth: dx (\S+) px, dy (\S+) px, total (\S+) px")


@pytest.mark.cluster
@pytest.mark.parametrize("where", ["local", "scheduler"])
def test_notebook_runs_and_matches_truth(tmp_path, request, where):
    import matplotlib.image as mpimg
    env = {k: v for k, v in os.environ.items() if k != "DASK_SCHEDULER_ADDRESS"}
    env.update({"MPLBACKEND": "Agg", "GEOCODER_EXAMPLE_SIZE": "512", "GEOCODER_EXAMPLE_DIR": str(tmp_path)})
    if where == "scheduler":  # an existing cluster, as a remote user would connect to it
        env["DASK_SCHEDULER_ADDRESS"] = request.getfixturevalue("client").scheduler.address
    r = subprocess.run([sys.executable, str(NOTEBOOK)], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "dashboard: http" in r.stdout

    for name in FIGURES:
        png = tmp_path / f"{name}.png"
        assert png.is_file(), f"{png} was not written"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        image = mpimg.imread(png)
        assert min(image.shape[:2]) > 200 and np.std(image[..., :3]) > 0.05, f"{png} looks empty"
    assert (tmp_path / "registered.zarr" / "zarr.json").is_file()

    found = RMSE.findall(r.stdout)
    assert len(found) == 1, r.stdout
    rmse_x, rmse_y, total = map(float, found[0])
    assert np.isfinite(total) and total == pytest.approx(np.hypot(rmse_x, rmse_y), abs=2e-4)
    assert total < 0.1, r.stdout


def test_notebook_is_a_jupytext_notebook():
    import jupytext
    import nbformat
    nb = jupytext.read(NOTEBOOK)
    kinds = [cell.cell_type for cell in nb.cells]
    assert kinds.count("code") >= 6 and kinds.count("markdown") >= 6, kinds
    assert kinds[0] == "markdown" and nb.cells[0].source.startswith("# ")
    assert nb.metadata["jupytext"]["formats"].startswith("py:percent")

    # to .ipynb and back: a valid notebook with the same cells, and the same script below the header
    ipynb = jupytext.writes(nb, fmt="ipynb")
    back = jupytext.reads(ipynb, fmt="ipynb")
    nbformat.validate(back)
    assert [(c.cell_type, c.source) for c in back.cells] == [(c.cell_type, c.source) for c in nb.cells]
    assert body(jupytext.writes(back, fmt="py:percent")) == body(NOTEBOOK.read_text())


def body(script: str) -> str:
    """The script without its YAML header (where jupytext records its own version)."""
    assert script.startswith("# ---\n")
    return script[script.index("\n# ---\n", 5) + 7 :]
