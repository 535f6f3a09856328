"""The registration report looked at in a real headless Chromium (issue 15 part 1's acceptance).

Two real register runs on the test cluster: a real pair (one Sentinel-2 band on two dates ten
days apart, both georeferenced, no truth) and a simulated one (a real S2 crop warped with
scan-line turbulence of known truth, as in ``test_report.py``). ``geocoder report`` writes the
page of each; Chromium (Debian's ``chromium-headless-shell`` or ``chromium``) loads it from a
``file://`` URL and is asked, over the DevTools protocol on a pipe, whether every figure is
decoded (``naturalWidth`` > 0, the PNG's own size), laid out on the page, and whether the page
logged any error. A full-page screenshot is kept, and every figure's region of it must hold the
figure's own pixels: that is what "shown" means. A report with a deleted and a truncated figure
shows that the check fails when a figure is not shown.

Skipped only when no Chromium is installed (``.ci/run`` installs it).
"""

from __future__ import annotations

import base64
import fcntl
import json
import os
import select
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from affine import Affine

pytestmark = [pytest.mark.cluster, pytest.mark.data]

BROWSERS = ("chromium-headless-shell", "chromium")
WIDTH, HEIGHT = 1300, 900  # the viewport: the page's max-width is 1300 px
S2_REF = "s2_arosics/ref_S2A_20160608T153121_T33UUU_sub.tif"
S2_TGT = "s2_arosics/tgt_S2A_20160529T153631_T33UUU_sub.tif"
#: The real pair's ground window (UTM 33N): free of the target's clouds and of both no-data wedges.
REAL_CORNER = (344000.0, 5847560.0)
SIZE = 256

#: Every <img>: its src, whether loading finished, its decoded size and its box on the page (CSS px).
IMAGES_JS = """JSON.stringify(Array.from(document.images, im => {
  const r = im.getBoundingClientRect(), s = getComputedStyle(im);
  return {src: im.getAttribute('src'), complete: im.complete, natural: [im.naturalWidth, im.naturalHeight],
          box: [r.left + window.scrollX + im.clientLeft, r.top + window.scrollY + im.clientTop,
                im.clientWidth, im.clientHeight],
          visible: s.display !== 'none' && s.visibility === 'visible' && Number(s.opacity) > 0};
}))"""


def chromium() -> str | None:
    """The first Chromium executable on PATH, None if there is none."""
    for name in BROWSERS:
        found = shutil.which(name)
        if found:
            return found
    return None

#: Run before Chromium, in its process: argv = [-c, read end, write end, chromium, arguments...].
WIRE = ("import os, sys; r, w = int(sys.argv[1]), int(sys.argv[2]); os.dup2(r, 3); os.dup2(w, 4); os.close(r); "
        "os.close(w); os.execv(sys.argv[3], sys.argv[3:])")


def _above(fd: int, lowest: int) -> int:
    """``fd`` moved to a descriptor number >= ``lowest`` (close-on-exec, as ``os.pipe`` makes them)."""
    moved = fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, lowest)
    os.close(fd)
    return moved


class Browser:
    """A headless Chromium driven over the DevTools protocol on a pipe (``--remote-debugging-pipe``).

    Messages are JSON texts ended by a NUL byte: the browser reads them on its file descriptor 3
    and writes on 4. One page target, attached in flat mode, receives the page commands.
    """

    def __init__(self, executable: str, profile: Path, timeout: float = 60.0) -> None:
        self.timeout = timeout
        # pipe ends at 10 and above, so that putting them on 3 and 4 in the child cannot clobber one of them
        to_browser_r, self._to_browser, self._from_browser, from_browser_w = (_above(fd, 10) for fd in (*os.pipe(), *os.pipe()))
        args = [executable, "--headless", "--remote-debugging-pipe", f"--user-data-dir={profile}", "--no-first-run",
                "--no-default-browser-check", "--disable-gpu", "--disable-dev-shm-usage", "--hide-scrollbars",
                "--disable-extensions", "--mute-audio", f"--window-size={WIDTH},{HEIGHT}", "about:blank"]
        if os.geteuid() == 0:  # Chromium's sandbox refuses to run as root (containers, CI)
            args.insert(1, "--no-sandbox")
        # a small Python puts the pipes on the descriptors Chromium expects, then becomes Chromium (no preexec_fn:
        # this process has threads)
        self.proc = subprocess.Popen([sys.executable, "-c", WIRE, str(to_browser_r), str(from_browser_w), *args],
                                     pass_fds=(to_browser_r, from_browser_w), stdin=subprocess.DEVNULL,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        os.close(to_browser_r)
        os.close(from_browser_w)
        self._buffer = b""
        self._next_id = 0
        self.events: list[dict] = []
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        self.session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        for domain in ("Page", "Runtime", "Log"):
            self.call(f"{domain}.enable", session=self.session)
        self.call("Emulation.setDeviceMetricsOverride", session=self.session, width=WIDTH, height=HEIGHT,
                  deviceScaleFactor=1, mobile=False)

    def _receive(self, deadline: float) -> dict:
        while b"\0" not in self._buffer:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._from_browser], [], [], left)[0]:
                raise TimeoutError(f"Chromium did not answer within {self.timeout:.0f} s")
            chunk = os.read(self._from_browser, 1 << 20)
            if not chunk:
                raise RuntimeError(f"Chromium closed its pipe: {self.proc.stderr.read().decode(errors='replace')[-2000:]}")
            self._buffer += chunk
        message, self._buffer = self._buffer.split(b"\0", 1)
        return json.loads(message)

    def call(self, method: str, *, session: str | None = None, **params) -> dict:
        """Send one command and return its result; events that arrive meanwhile are kept in order."""
        self._next_id += 1
        message = {"id": self._next_id, "method": method, "params": params}
        if session:
            message["sessionId"] = session
        os.write(self._to_browser, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + self.timeout
        while True:
            reply = self._receive(deadline)
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})
            self.events.append(reply)

    def load(self, url: str) -> None:
        """Navigate to ``url`` and wait for its load event (every image fetched and decoded or failed)."""
        self.events.clear()
        self.call("Page.navigate", session=self.session, url=url)
        deadline = time.monotonic() + self.timeout
        while not any(e.get("method") == "Page.loadEventFired" for e in self.events):
            self.events.append(self._receive(deadline))

    def evaluate(self, expression: str):
        """The JSON value of a JavaScript expression evaluated in the page."""
        result = self.call("Runtime.evaluate", session=self.session, expression=expression, returnByValue=True)
        if "exceptionDetails" in result:
            raise RuntimeError(f"{expression[:60]}...: {result['exceptionDetails']}")
        return result["result"]["value"]

    def errors(self) -> list[str]:
        """Errors the page reported since it was loaded: console errors, uncaught exceptions, failed loads."""
        out = []
        for e in self.events:
            method, p = e.get("method"), e.get("params", {})
            if method == "Log.entryAdded" and p["entry"]["level"] == "error":
                out.append(f"{p['entry']['text']} {p['entry'].get('url', '')}".strip())
            elif method == "Runtime.consoleAPICalled" and p["type"] in ("error", "assert"):
                out.append(" ".join(str(a.get("value", a.get("description", ""))) for a in p["args"]))
            elif method == "Runtime.exceptionThrown":
                out.append(p["exceptionDetails"].get("text", "exception"))
        return out

    def screenshot(self, path: Path) -> None:
        """A PNG of the whole page, not only the viewport."""
        shot = self.call("Page.captureScreenshot", session=self.session, format="png", captureBeyondViewport=True)
        path.write_bytes(base64.b64decode(shot["data"]))

    def close(self) -> None:
        try:
            self.call("Browser.close")
        except (RuntimeError, TimeoutError, OSError):
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        for fd in (self._to_browser, self._from_browser):
            os.close(fd)
        self.proc.stderr.close()


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    executable = chromium()
    if executable is None:
        pytest.skip("Chromium is not installed (none of " + ", ".join(BROWSERS) + " on PATH); "
                    "apt-get install --no-install-recommends chromium-headless-shell")
    b = Browser(executable, tmp_path_factory.mktemp("chromium-profile"))
    yield b
    b.close()


def _write_real_pair(shared: Path, d: Path) -> tuple[Path, Path]:
    """The same ground on two dates: the base cropped from one, the other with a 32 px margin, both georeferenced."""
    import rasterio
    from conftest import read_band

    from geocoder.scene import write_geotiff

    out = []
    for name, path, margin in (("real-base", S2_REF, 0), ("real-distorted", S2_TGT, 32)):
        with rasterio.open(shared / path) as f:
            col, row = (round(v) - margin for v in ~f.transform * REAL_CORNER)
            transform, crs = f.transform * Affine.translation(col, row), f.crs
        img = read_band(shared / path, 1, (row, row + SIZE + 2 * margin, col, col + SIZE + 2 * margin))
        assert (img > 0).all(), f"{path}: the crop must be free of no-data"
        out.append(d / f"{name}.tif")
        write_geotiff(out[-1], img.astype(np.uint16), transform=transform, crs=crs)
    return out[0], out[1]


@pytest.fixture(scope="module")
def reports(shared_data, tmp_path_factory, client, s2_turbulence):
    """Report directories of a real and of a simulated pair, registered on the test cluster.

    The simulated one (a real S2 crop of SIZE px, seed 21, turbulence (1, 3), tile 128, the report
    against the truth) is the session's ``s2_turbulence``, the run test_report.py looks at.
    """
    from geocoder import register, report

    d = tmp_path_factory.mktemp("browser")
    base, dist = _write_real_pair(shared_data, d)
    register(base, dist, out=d / "real.zarr", tile=128, client=client, show_progress=False)
    report(d / "real.zarr", d / "real-report")
    _, _, files, simulated = s2_turbulence
    assert files.pair.dx.shape == (SIZE, SIZE)
    return {"real": d / "real-report", "simulated": Path(simulated)}


def _look(browser: Browser, directory: Path, shot: Path) -> tuple[list[dict], list[str], np.ndarray]:
    """Load a report's page; its images as the page sees them, its errors and its screenshot (RGB, 0-1)."""
    import matplotlib.image as mpimg

    browser.load((directory / "report.html").resolve().as_uri())
    images = json.loads(browser.evaluate(IMAGES_JS))
    browser.screenshot(shot)
    return images, browser.errors(), mpimg.imread(shot)[..., :3]


def _shown(image: dict, directory: Path, screen: np.ndarray) -> float:
    """Mean absolute difference (0-1) between the figure's PNG in ``directory``, scaled to its box, and the screenshot there.

    A box at a fractional position is drawn snapped to the pixel grid: the best of the offsets
    within a pixel of it is taken. Both are compared in 4 x 4 blocks, so that the browser's
    resampling of a figure scaled to the page's width differs from ours only in fine detail.
    """
    from PIL import Image

    def blocks(a: np.ndarray, k: int = 4) -> np.ndarray:
        h, w = a.shape[0] // k * k, a.shape[1] // k * k
        return a[:h, :w].reshape(h // k, k, w // k, k, -1).mean(axis=(1, 3))

    x, y, w, h = (round(v) for v in image["box"])
    with Image.open(directory / image["src"]) as png:
        expected = blocks(np.asarray(png.convert("RGB").resize((w, h), Image.Resampling.BILINEAR), dtype=np.float64) / 255)
    return min(float(np.mean(np.abs(blocks(screen[y + dy:y + dy + h, x + dx:x + dx + w]) - expected)))
               for dy in (-1, 0, 1) for dx in (-1, 0, 1))


@pytest.mark.parametrize("which", ["real", "simulated"])
def test_every_figure_is_shown_in_chromium(browser, reports, which, tmp_path):
    from PIL import Image

    directory = reports[which]
    shot = tmp_path / f"{which}-report.png"
    images, errors, screen = _look(browser, directory, shot)
    pngs = sorted(p.name for p in directory.glob("*.png"))
    assert len(pngs) == (8 if which == "simulated" else 7)  # the truth adds the error map
    assert sorted(im["src"] for im in images) == pngs  # one <img> per figure written, each figure once
    assert errors == []
    for im in images:
        with Image.open(directory / im["src"]) as png:
            size = list(png.size)
            rgb = np.asarray(png.convert("RGB"))
        rim = np.concatenate([rgb[:3].reshape(-1, 3), rgb[-3:].reshape(-1, 3), rgb[:, :3].reshape(-1, 3),
                              rgb[:, -3:].reshape(-1, 3)])
        assert (rim == 255).all(), f"{im['src']}: something is cut off at the figure's edge"
        assert im["complete"] and im["natural"] == size, im  # decoded, at the PNG's own size
        assert im["visible"] and im["box"][2] > 300 and im["box"][3] > 200, im  # laid out, large enough to read
        assert im["box"][2] <= WIDTH and im["box"][2] / im["box"][3] == pytest.approx(size[0] / size[1], rel=0.01)
    # the screenshot is the whole page, not a blank one, and every figure's box holds that figure's pixels
    height = browser.evaluate("document.documentElement.scrollHeight")
    assert screen.shape[:2] == (height, WIDTH) and height > sum(im["box"][3] for im in images)
    assert float(screen.std()) > 0.1 and len(np.unique(screen.reshape(-1, 3)[::97], axis=0)) > 50
    for im in images:
        assert _shown(im, directory, screen) < 0.03, im["src"]


def test_a_missing_or_truncated_figure_is_caught(browser, reports, tmp_path):
    """The same checks on a report with one figure deleted and one cut short must fail for those two."""
    broken = tmp_path / "broken"
    shutil.copytree(reports["simulated"], broken)
    (broken / "status.png").unlink()
    hsi = (broken / "hsi.png").read_bytes()
    (broken / "hsi.png").write_bytes(hsi[: len(hsi) // 4])  # a quarter of the file: the top rows only
    images, errors, screen = _look(browser, broken, tmp_path / "broken.png")
    by_src = {im["src"]: im for im in images}
    assert by_src["status.png"]["natural"] == [0, 0]
    assert any("ERR_FILE_NOT_FOUND" in e and e.endswith("status.png") for e in errors), errors
    intact = reports["simulated"]
    assert _shown(by_src["hsi.png"], intact, screen) > 0.05  # decoded in part: the screen is not the figure
    for name in ("disparity.png", "error.png", "tiepoints.png"):
        assert _shown(by_src[name], intact, screen) < 0.03, name
