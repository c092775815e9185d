"""The HTML report: content, self-containment, and a real headless browser (Debian's chromium).

The browser tests drive Chromium over the DevTools protocol on a pipe
(``--remote-debugging-pipe``: NUL-separated JSON on file descriptors 3 and 4),
so they need no Python package beyond the standard library. They are marked
``browser`` and skip when no ``chromium`` executable is found (set
``STICKFIGURE_CHROMIUM`` to its path if it is not on PATH).
"""

from __future__ import annotations

import base64
from html import unescape
import fcntl
import json
import os
import re
import select
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

import stickfigure as sf
from stickfigure.report import render_report, write_report
from stickfigure.report._data import player_data
from stickfigure.track import track_video


# ------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def figure_and_model():
    """An occluded synthetic figure and a mi-tree model given its true segmentation (fast)."""
    occ, skel, _ = _figure_model_truth()
    return occ, skel


def _figure_model_truth():
    traj = sf.synthetic.random_figure(n_sticks=4, frames=50, seed=3)
    occ, _ = sf.synthetic.occlude(traj, seed=1)
    skel = sf.fit(occ, method="mi-tree", labels=traj.labels_true, random_state=0)
    return occ, skel, traj


def _stage_skeleton(traj: sf.Trajectories) -> sf.Skeleton:
    """A skeleton as a merge-stage method would report it (the true structure, info with per-stage numbers)."""
    return sf.Skeleton(
        method="no-such-method", labels=traj.labels_true, n_sticks=traj.n_parts_true, edges=traj.edges_true,
        joints=traj.joints_true, log_likelihood=-123.5,
        info={"stages": [{"stage": k, "n_sticks": 5 - k, "objective": -200.0 + 30 * k,
                          "labels": list(range(29))} for k in range(4)], "selected_stage": 3,
              "objective": [-200.0, -170.0, -140.0, -123.5], "mutual_information": [[0, 1.5], [1.5, 0]],
              "converged": True, "note": "hand-made for the test"},
    )


def _page_data(html: str) -> dict:
    m = re.search(r'<script type="application/json" id="report-data">(.*?)</script>', html, re.S)
    assert m, "no data block"
    return json.loads(m.group(1))


# ------------------------------------------------------------------- content
def test_report_is_self_contained(tmp_path, figure_and_model):
    traj, skel = figure_and_model
    path = write_report(skel, traj, tmp_path / "r.html", title="My <figure>")
    html = path.read_text(encoding="utf-8")
    assert html.startswith("<!DOCTYPE html>")
    assert "<title>My &lt;figure&gt;</title>" in html
    # Nothing is fetched: no external URLs in src/href, images are data URIs, a CSP forbids the rest.
    assert not re.search(r'(src|href)="(?!data:|#)', html)
    assert not re.search(r"https?://", html)
    assert "default-src 'none'" in html
    imgs = re.findall(r'<img src="([^"]+)"', html)
    assert imgs and all(u.startswith("data:image/png;base64,") for u in imgs)
    for u in imgs:  # each embedded PNG decodes to a real picture
        png = base64.b64decode(u.split(",", 1)[1])
        img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        assert img is not None and img.shape[0] > 50 and img.shape[1] > 50 and img.std() > 5
    # No template placeholder left behind.
    assert "{{" not in html.replace("{{", "", 0) or not re.search(r"\{\{\w+\}\}", html)


def test_report_tables_and_player_data(figure_and_model):
    traj, skel = figure_and_model
    html = render_report(skel, traj)
    data = _page_data(html)["players"]["main"]
    P, F = traj.n_points, traj.n_frames
    assert data["n_frames"] == F and len(data["points"]) == F and len(data["points"][0]) == 2 * P
    assert data["labels"] == skel.labels.tolist()
    assert len(data["colors"]) == skel.n_sticks
    assert len(data["joints"]) == skel.n_joints
    # Observed entries are shown where they are, missing ones are null (and filled in by the model).
    pts = np.array([[np.nan if v is None else v for v in row] for row in data["points"]])
    np.testing.assert_allclose(pts.reshape(F, P, 2).transpose(1, 0, 2), traj.xy, atol=1e-3 * np.nanmax(np.abs(traj.xy)))
    assert data["imputed"] is not None
    # The stick table lists every stick with its number of points.
    sizes = skel.stick_sizes()
    for s in range(skel.n_sticks):
        assert re.search(rf"S{s}</td><td class=\"num\">{sizes[s]}</td>", html)
    assert html.count("<tr><td>S") >= len(skel.edges)  # joints table rows
    # Method diagnostics from stickfigure.plot.mitree, and the quality section.
    assert "mutual information" in html.lower()
    assert "imputation RMSE" in html and "linear interpolation" in html
    assert "adjusted Rand index" in html


def test_report_scores_hidden_entries_against_truth():
    occ, skel, full = _figure_model_truth()
    from stickfigure.report._data import impute, quality

    q = quality(skel, occ, truth=full)
    hidden = ~occ.observed
    filled = impute(skel, occ)
    err = np.sqrt(np.mean(np.sum((filled[hidden] - full.xy[hidden]) ** 2, axis=1)))
    assert q["hidden"]["n_hidden"] == int(hidden.sum())
    assert q["hidden"]["rmse"] == pytest.approx(err)
    html = unescape(render_report(skel, occ, truth=full))
    assert f"error on the {int(hidden.sum())} entries missing from the input" in html
    with pytest.raises(ValueError, match="truth"):
        quality(skel, occ, truth=full.xy[:, :10])


def test_report_without_plot_module_shows_raw_info(figure_and_model):
    traj, _ = figure_and_model
    skel = _stage_skeleton(traj)
    html = unescape(render_report(skel, traj))
    assert "has no module for 'no-such-method'" in html
    # Per-stage records become a table (the selected stage marked, long lists summarised by their
    # shape), the objective series a sparkline, the matrix a shaded table.
    assert "<h3>stages</h3>" in html and html.count("<td class=\"num\">-170</td>") == 1
    assert "3 ◀ selected" in html
    assert "[29 values]" in html
    assert "<svg class=\"spark\"" in html
    assert "<h3>mutual_information</h3>" in html
    # Quality: no motions, no impute for an unknown method -> said, not raised.
    assert "impute" in html and "unknown method" in html
    assert "adjusted Rand index" in html


def _tiny_video(path: Path, n: int = 12) -> str:
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (96, 64))
    for f in range(n):
        img = np.full((64, 96, 3), 40, np.uint8)
        cv2.circle(img, (10 + 5 * f, 32), 6, (0, 200, 255), -1)
        w.write(img)
    w.release()
    return str(path)


def test_report_over_video_frames(tmp_path):
    video = _tiny_video(tmp_path / "v.avi", 12)
    rng = np.random.default_rng(0)
    xy = np.stack([np.stack([10 + 5 * np.arange(8) + dx, 32 + np.zeros(8) + dy], axis=1)
                   for dx, dy in rng.uniform(-3, 3, size=(6, 2))])
    traj = sf.Trajectories(xy, image_size=(96, 64), frame_rate=10, video=video, meta={"frame_offset": 2})
    skel = sf.Skeleton(method="x", labels=np.zeros(6, int), n_sticks=1)
    data = player_data(skel, traj)
    assert len(data["backgrounds"]) == 8
    assert data["frame_numbers"] == list(range(2, 10))
    # The embedded frames are the video's frames 2..9 (the disc moves 5 px per frame).
    for k in (0, 7):
        jpg = base64.b64decode(data["backgrounds"][k].split(",", 1)[1])
        img = cv2.imdecode(np.frombuffer(jpg, np.uint8), cv2.IMREAD_COLOR)
        col = np.flatnonzero(img[32, :, 2] > 150)
        assert abs(col.mean() - (10 + 5 * (k + 2))) < 2
    # A video that cannot be read: points drawn alone, and the page says so.
    gone = traj.copy(video=str(tmp_path / "missing.avi"))
    html = render_report(skel, gone)
    assert "backgrounds" not in _page_data(html)["players"]["main"]
    assert "could not be read" in html


def _small_figure_in_big_frame() -> tuple[sf.Skeleton, sf.Trajectories]:
    rng = np.random.default_rng(1)
    xy = 500 + rng.normal(size=(8, 10, 2)) * 10 + np.arange(10)[None, :, None]
    traj = sf.Trajectories(xy, image_size=(1000, 1000), frame_rate=10)
    return sf.Skeleton(method="x", labels=np.repeat([0, 1], 4), n_sticks=2), traj


def test_player_zooms_to_a_small_figure(figure_and_model):
    skel, traj = _small_figure_in_big_frame()
    x0, y0, w, h = player_data(skel, traj)["focus"]
    pts = traj.xy.reshape(-1, 2)
    assert x0 < pts[:, 0].min() and x0 + w > pts[:, 0].max() and y0 < pts[:, 1].min() and y0 + h > pts[:, 1].max()
    assert w * h < 0.1 * 1000 * 1000
    # A figure filling the frame, or data without an image: no zoom.
    big = traj.with_xy(np.random.default_rng(2).uniform(50, 950, size=traj.xy.shape))
    assert player_data(skel, big)["focus"] is None
    t2, s2 = figure_and_model
    assert player_data(s2, t2)["focus"] is None


def test_report_caps_frames(figure_and_model):
    traj, skel = figure_and_model
    data = player_data(skel, traj, max_frames=20)
    assert data["n_frames"] <= 20 and data["step"] == 3


def test_report_bad_input(tmp_path, figure_and_model):
    traj, skel = figure_and_model
    with pytest.raises(ValueError, match="points"):
        write_report(skel, traj.slice(points=slice(0, 5)), tmp_path / "r.html")
    with pytest.raises(ValueError, match="frames"):
        write_report(skel, traj.slice(frames=slice(0, 10)), tmp_path / "r.html")
    with pytest.raises(ValueError, match="directory"):
        write_report(skel, traj, tmp_path)
    with pytest.raises(TypeError, match="Skeleton"):
        write_report("model.json", traj, tmp_path / "r.html")


def test_report_write_is_atomic(tmp_path, figure_and_model, monkeypatch):
    traj, skel = figure_and_model
    path = tmp_path / "r.html"
    path.write_text("old", encoding="utf-8")
    import stickfigure.report as rep

    def boom(*a, **k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(rep, "render_report", boom)
    with pytest.raises(RuntimeError):
        rep.write_report(skel, traj, path)
    assert path.read_text(encoding="utf-8") == "old"
    monkeypatch.undo()
    write_report(skel, traj, path)
    assert path.read_text(encoding="utf-8").startswith("<!DOCTYPE html>")
    assert [p.name for p in tmp_path.iterdir()] == ["r.html"]  # no temporary file left


# ------------------------------------------------------------------ browser
def _chromium() -> str | None:
    exe = os.environ.get("STICKFIGURE_CHROMIUM")
    if exe:
        return exe if Path(exe).exists() else None
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        found = shutil.which(name)
        if found:
            return found
    return None


CHROMIUM = _chromium()
if CHROMIUM is None and os.environ.get("STICKFIGURE_REQUIRE_BROWSER"):
    raise RuntimeError("STICKFIGURE_REQUIRE_BROWSER is set but no Chromium was found (apt-get install -y chromium "
                       "or set STICKFIGURE_CHROMIUM)")
needs_browser = pytest.mark.skipif(
    CHROMIUM is None,
    reason="no headless Chromium found: install Debian's chromium (apt-get install -y chromium) "
           "or set STICKFIGURE_CHROMIUM",
)
_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
          "--disable-background-networking", "--disable-component-update", "--disable-sync",
          "--disable-dev-shm-usage", "--hide-scrollbars"]


class Browser:
    """Headless Chromium over the DevTools protocol on a pipe (no websocket, no extra package)."""

    def __init__(self, exe: str, width: int = 1280, height: int = 900) -> None:
        self.tmp = tempfile.mkdtemp(prefix="sf-chromium-")
        r_in, self.w = os.pipe()  # commands: we write, Chromium reads them on its fd 3
        self.r, w_out = os.pipe()  # replies and events: Chromium writes them on its fd 4
        # Above 9 and close-on-exec, so moving them to 3 and 4 in the child cannot clash.
        c_in, c_out = fcntl.fcntl(r_in, fcntl.F_DUPFD_CLOEXEC, 10), fcntl.fcntl(w_out, fcntl.F_DUPFD_CLOEXEC, 10)
        os.close(r_in)
        os.close(w_out)

        def to_3_and_4() -> None:  # runs in the child before exec
            os.dup2(c_in, 3)
            os.dup2(c_out, 4)

        self.log = open(Path(self.tmp) / "stderr.txt", "wb")
        self.proc = subprocess.Popen(
            [exe, *_FLAGS, f"--user-data-dir={self.tmp}/profile", "--remote-debugging-pipe",
             f"--window-size={width},{height}", "about:blank"],
            close_fds=False, preexec_fn=to_3_and_4, stdin=subprocess.DEVNULL, stdout=self.log, stderr=self.log)
        os.close(c_in)
        os.close(c_out)
        self.buf = b""
        self.next_id = 0
        self.events: list[dict] = []

    def _read(self, timeout: float) -> dict:
        deadline = time.monotonic() + timeout
        while b"\0" not in self.buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("no answer from Chromium")
            if select.select([self.r], [], [], left)[0]:
                chunk = os.read(self.r, 1 << 20)
                if not chunk:
                    raise RuntimeError("Chromium exited: " + (Path(self.tmp) / "stderr.txt").read_text(errors="replace")[-1500:])
                self.buf += chunk
        msg, self.buf = self.buf.split(b"\0", 1)
        return json.loads(msg)

    def send(self, method: str, params: dict | None = None, session: str | None = None, timeout: float = 30) -> dict:
        self.next_id += 1
        msg = {"id": self.next_id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        os.write(self.w, json.dumps(msg).encode() + b"\0")
        while True:
            r = self._read(timeout)
            if r.get("id") == self.next_id:
                if "error" in r:
                    raise RuntimeError(f"{method}: {r['error']}")
                return r.get("result", {})
            self.events.append(r)

    def wait_for(self, event: str, timeout: float = 30) -> dict:
        for e in self.events:
            if e.get("method") == event:
                return e
        deadline = time.monotonic() + timeout
        while True:
            r = self._read(max(0.01, deadline - time.monotonic()))
            self.events.append(r)
            if r.get("method") == event:
                return r

    def open(self, url: str, width: int = 1280, height: int = 900) -> str:
        target = self.send("Target.createTarget", {"url": "about:blank"})["targetId"]
        s = self.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        for m in ("Runtime.enable", "Log.enable", "Page.enable", "Network.enable"):
            self.send(m, session=s)
        self.send("Emulation.setDeviceMetricsOverride",
                  {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False}, session=s)
        self.send("Page.navigate", {"url": url}, session=s)
        self.wait_for("Page.loadEventFired", timeout=60)
        return s

    def js(self, session: str, expr: str):
        r = self.send("Runtime.evaluate", {"expression": expr, "returnByValue": True, "awaitPromise": True},
                      session=session)
        if "exceptionDetails" in r:
            raise RuntimeError(f"page script failed: {r['exceptionDetails']}")
        return r["result"].get("value")

    def problems(self) -> list[str]:
        """Console errors/warnings, uncaught exceptions, and requests for anything but the page and data: URIs."""
        out = []
        for e in self.events:
            m, p = e.get("method"), e.get("params", {})
            if m == "Runtime.exceptionThrown":
                out.append("exception: " + json.dumps(p.get("exceptionDetails", {}))[:300])
            elif m == "Runtime.consoleAPICalled" and p.get("type") in ("error", "warning", "assert"):
                out.append(f"console.{p['type']}: " + json.dumps(p.get("args", []))[:300])
            elif m == "Log.entryAdded" and p["entry"].get("level") in ("error", "warning"):
                out.append("log: " + p["entry"].get("text", "")[:300])
            elif m == "Network.requestWillBeSent":
                url = p["request"]["url"]
                if not (url.startswith("data:") or url.startswith("file://") or url == "about:blank"):
                    out.append("request: " + url[:200])
        return out

    def close(self) -> None:
        try:
            self.send("Browser.close", timeout=5)
        except Exception:
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        for fd in (self.w, self.r):
            os.close(fd)
        self.log.close()
        shutil.rmtree(self.tmp, ignore_errors=True)


@pytest.fixture(scope="module")
def browser():
    b = Browser(CHROMIUM)  # type: ignore[arg-type]
    yield b
    b.close()


@pytest.fixture(scope="module")
def video_report(tmp_path_factory):
    """A report over real video frames: tracks of a synthetic video, a mi-tree model given a segmentation."""
    d = tmp_path_factory.mktemp("vid")
    path = d / "blobs.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (160, 120))
    rng = np.random.default_rng(5)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (40, 40)).astype(np.float32), (0, 0), 1.5).astype(np.uint8)
    for f in range(30):
        img = np.full((120, 160), 30, np.uint8)
        for k, (x0, v) in enumerate(((10, 1.5), (80, -1.0))):
            x = int(x0 + v * f) + (0 if k == 0 else 20)
            img[40 + 20 * k:80 + 20 * k, x:x + 40] = tex
        w.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    w.release()
    traj = track_video(path, min_length=5)
    labels = (np.nanmean(traj.xy[..., 0], axis=1) > np.nanmedian(traj.xy[..., 0])).astype(int)
    skel = sf.fit(traj.drop_unobserved(), method="mi-tree", labels=labels, random_state=0)
    return write_report(skel, traj, d / "video.html")


def _check_page(browser: Browser, path: Path) -> tuple[str, dict]:
    browser.events.clear()
    s = browser.open(path.as_uri())
    deadline = time.monotonic() + 30
    while browser.js(s, "document.documentElement.dataset.selfcheck") == "pending":
        assert time.monotonic() < deadline, "the page never finished its self-check"
        time.sleep(0.05)
    state = browser.js(s, "Object.assign({}, document.documentElement.dataset)")
    return s, state


@pytest.mark.browser
@needs_browser
def test_report_loads_without_errors_in_chromium(browser, tmp_path, figure_and_model):
    traj, skel = figure_and_model
    path = write_report(skel, traj, tmp_path / "r.html")
    s, state = _check_page(browser, path)
    assert state["selfcheck"] == "ok", state.get("errors")
    assert browser.problems() == []
    # Every <img> decoded, and the player's canvas shows a picture (not one flat colour).
    n_img = browser.js(s, "Array.from(document.images).filter(i => i.complete && i.naturalWidth > 0).length")
    assert n_img == len(re.findall(r"<img ", path.read_text(encoding="utf-8"))) >= 2
    spread = browser.js(s, """(() => { const c = document.querySelector('.player canvas');
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; const seen = new Set();
        for (let i = 0; i < d.length; i += 4 * 97) seen.add(d[i] + ',' + d[i+1] + ',' + d[i+2]);
        return seen.size; })()""")
    assert spread > 5
    # The controls work: stepping and playing move the frame.
    label0 = browser.js(s, "document.querySelector('.player .frame').textContent")
    browser.js(s, "document.querySelector('.player button.next').click()")
    assert browser.js(s, "document.querySelector('.player .frame').textContent") != label0
    browser.js(s, "document.querySelector('.player button.play').click()")
    before = browser.js(s, "document.querySelector('.player input.seek').value")
    time.sleep(0.5)
    after = browser.js(s, "document.querySelector('.player input.seek').value")
    browser.js(s, "document.querySelector('.player button.play').click()")
    assert after != before
    assert browser.problems() == []


@pytest.mark.browser
@needs_browser
def test_report_over_video_in_chromium(browser, video_report):
    s, state = _check_page(browser, video_report)
    assert state["selfcheck"] == "ok", state.get("errors")
    assert int(state["videoFrames"]) == 30
    assert browser.problems() == []
    # With the video layer on, the canvas shows the video's grey background; off, the plain dark one.
    sample = "(() => { const c = document.querySelector('.player canvas'); " \
             "return Array.from(c.getContext('2d').getImageData(2, 2, 1, 1).data.slice(0, 3)); })()"
    with_video = browser.js(s, sample)
    browser.js(s, "(() => { const b = document.querySelector('input[data-layer=video]'); b.click(); })()")
    without = browser.js(s, sample)
    assert abs(with_video[0] - 30) < 12 and without[0] < 20


@pytest.mark.browser
@needs_browser
def test_report_zoom_in_chromium(browser, tmp_path):
    skel, traj = _small_figure_in_big_frame()
    s, state = _check_page(browser, write_report(skel, traj, tmp_path / "zoom.html"))
    assert state["selfcheck"] == "ok", state.get("errors")
    size = "(() => { const c = document.querySelector('.player canvas'); return [c.width, c.height]; })()"
    zoomed = browser.js(s, size)
    assert browser.js(s, "document.querySelector('input[data-layer=zoom]').checked") is True
    browser.js(s, "document.querySelector('input[data-layer=zoom]').click()")
    full = browser.js(s, size)
    assert full == [720, 720]  # the whole 1000 x 1000 frame, fitted into 960 x 720
    assert zoomed != full
    assert browser.problems() == []


@pytest.mark.browser
@needs_browser
def test_report_screenshot(tmp_path, figure_and_model):
    traj, skel = figure_and_model
    page = write_report(skel, traj, tmp_path / "r.html")
    shot = tmp_path / "shot.png"
    profile = tmp_path / "profile"
    subprocess.run([CHROMIUM, *_FLAGS, f"--user-data-dir={profile}", f"--screenshot={shot}",
                    "--window-size=1280,2400", "--virtual-time-budget=3000", page.as_uri()],
                   check=True, timeout=120, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    img = cv2.imread(str(shot))
    assert img is not None and img.shape[:2] == (2400, 1280)
    # Not blank: the dark header, white cards and the coloured figures are all there.
    assert img.std() > 20
    assert (img.reshape(-1, 3) < 60).all(axis=1).mean() > 0.01  # header / canvas
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
    assert (hsv[..., 1] > 120).mean() > 0.001  # saturated stick colours


def test_report_gives_the_data_s_articulation():
    """The input table says how much the clip bends: the still demo walker far less than a random figure."""
    from stickfigure.demo import make_figure
    from stickfigure.geometry import articulation

    shown = {}
    for name in ("walker", "random"):
        traj = make_figure(name, n_frames=30)
        skel = sf.fit(traj, method="mi-tree", labels=traj.labels_true, random_state=0)
        html = unescape(render_report(skel, traj))
        m = re.search(r"([0-9.]+)% of the motion departs from one rigid body", html)
        assert m, name
        shown[name] = float(m.group(1))
        assert shown[name] == pytest.approx(100 * articulation(traj.xy), abs=0.051)
    assert shown["walker"] < 10.0 < shown["random"]
    # A point never seen is left out of the measure, not an error.
    from stickfigure.report._data import quality

    xy = traj.xy.copy()
    xy[0] = np.nan
    q = quality(skel, traj.with_xy(xy), hide=0)
    assert "articulation_error" not in q and np.isfinite(q["articulation"])


def test_report_names_the_camera_of_a_projection():
    """3D data projected for the fit: the input table says from where, and through which camera."""
    walker3d = sf.synthetic.walker(n_frames=20, seed=0, project=False)
    for distance, camera in ((None, "orthographic camera"), (5.0, "pinhole camera 5 from the scene centre")):
        traj = walker3d.project((30.0, 20.0), distance=distance)
        skel = sf.fit(traj, method="mi-tree", labels=traj.labels_true, random_state=0)
        html = unescape(render_report(skel, traj))
        assert f"3D data seen from azimuth 30°, elevation 20°, {camera}" in html
