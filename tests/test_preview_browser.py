"""The preview page in a real browser: a running daemon on the synthetic source serves it, a
headless Chromium (Debian's package, driven over the DevTools protocol) loads it; the
screenshot shows the marker with its overlay, and the page's pose readout is /status.json's."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest
from cdp import Browser, chromium_path

ROOT = Path(__file__).resolve().parents[1]

CONFIG = """
[camera]
source = "synthetic"
fps = {fps}
[pipeline]
status_interval_s = 60.0
[preview]
listen = "127.0.0.1:0"
data_dir = "{data}"
[output.jsonl]
path = "{poses}"
"""


@pytest.fixture
def chromium():
    if chromium_path() is None:
        if os.environ.get("CI") == "true":
            pytest.fail("chromium is missing in CI: scripts/ci-packages.sh installs it")
        pytest.skip("chromium is not installed (scripts/ci-packages.sh installs it)")


@pytest.fixture
def daemon(tmp_path):
    procs = []

    def start(fps: float):
        cfg = tmp_path / "preview.toml"
        cfg.write_text(CONFIG.format(fps=fps, data=tmp_path / "data", poses=tmp_path / "poses.jsonl"))
        log = open(tmp_path / "daemon.log", "w")
        proc = subprocess.Popen(
            [sys.executable, "-m", "pose_daemon", "run", "--config", str(cfg)],
            stdout=subprocess.DEVNULL,
            stderr=log,
            cwd=tmp_path,
        )
        procs.append(proc)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            text = (tmp_path / "daemon.log").read_text()
            m = re.search(r"preview on (http://127\.0\.0\.1:\d+/)", text)
            if m and "first frame processed" in text:
                return proc, m.group(1)
            assert proc.poll() is None, text
            time.sleep(0.1)
        raise AssertionError("the daemon did not start: " + (tmp_path / "daemon.log").read_text())

    yield start
    for p in procs:
        if p.poll() is None:
            p.kill()
            p.wait(10)


def _status(url):
    with urllib.request.urlopen(url + "status.json", timeout=10) as r:
        return json.loads(r.read())


def _until(fn, timeout_s=90.0):
    deadline = time.monotonic() + timeout_s
    while True:
        value = fn()
        if value or time.monotonic() > deadline:
            return value
        time.sleep(0.2)


# Empty until every element read is there: a loaded machine's browser runs this while it is
# still parsing the page ('frame' there, 'pos-x' not yet: a TypeError once so).
READOUT = """['frame', 'pos-x', 'pos-y', 'pos-z', 'alpha', 'beta', 'gamma', 'reproj', 'live']
  .some(id => !document.getElementById(id)) ? JSON.stringify({frame: '', img: 0}) :
  JSON.stringify({frame: document.getElementById('frame').dataset.frame,
  x: document.getElementById('pos-x').textContent, y: document.getElementById('pos-y').textContent,
  z: document.getElementById('pos-z').textContent, alpha: document.getElementById('alpha').textContent,
  beta: document.getElementById('beta').textContent, gamma: document.getElementById('gamma').textContent,
  reproj: document.getElementById('reproj').textContent,
  warnings: Array.from(document.querySelectorAll('#warnings li')).map(li => li.dataset.code || ''),
  img: document.getElementById('live').naturalWidth})"""


def test_the_page_shows_the_marker_with_its_overlay_and_the_pose_of_status_json(chromium, daemon, tmp_path):
    proc, url = daemon(fps=2.0)
    browser = Browser(tmp_path / "profile")
    try:
        browser.call("Page.enable")
        browser.call("Page.navigate", url=url)
        ready = _until(
            lambda: (lambda r: r if r["frame"] and r["img"] > 0 else None)(json.loads(browser.evaluate(READOUT)))
        )
        assert ready, "the page never showed a frame and a pose"

        # The readout is the pose of the frame it names, as /status.json gives it.
        def matched():
            shown = json.loads(browser.evaluate(READOUT))
            data = _status(url)
            last = data["last"]
            if last is None or str(last["frame"]) != shown["frame"]:
                return None
            return shown, data

        found = _until(matched)
        assert found, "the page's frame never matched /status.json's"
        shown, data = found
        last = data["last"]
        assert last["ok"], last
        x, y, z = last["camera_position"]
        assert (shown["x"], shown["y"], shown["z"]) == (f"{x:+.3f}", f"{y:+.3f}", f"{z:+.3f}")
        assert (shown["alpha"], shown["beta"], shown["gamma"]) == tuple(
            f"{last[k]:+.1f}" for k in ("alpha_deg", "beta_deg", "gamma_deg")
        )
        assert shown["reproj"] == f"{last['reprojection_error_px']:.2f} px"

        # The screenshot: the live image with the overlay where /status.json has the corners.
        rect = json.loads(
            browser.evaluate(
                "JSON.stringify((r => ({x: r.x, y: r.y, w: r.width, h: r.height}))"
                "(document.getElementById('live').getBoundingClientRect()))"
            )
        )
        png = browser.screenshot_png()
        # The corners the page had at that moment (the stream and the poll may be a frame apart).
        corners = np.array(json.loads(browser.evaluate("JSON.stringify(window.lastStatus.last.corners)")))
        shot = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        x0, y0 = int(round(rect["x"])), int(round(rect["y"]))
        view = shot[y0 : y0 + int(rect["h"]), x0 : x0 + int(rect["w"])].astype(int)
        assert view.shape[1] == 640, rect
        b, g, r = view[:, :, 0], view[:, :, 1], view[:, :, 2]
        green = (g > 170) & (r < 100) & (b < 100)  # the detected outline
        red = (r > 170) & (g < 100) & (b < 100)  # x axis, TL ring
        blue = (b > 170) & (r < 100) & (g < 120)  # z axis, BR ring
        assert green.sum() > 150 and red.sum() > 20 and blue.sum() > 10, (green.sum(), red.sum(), blue.sum())
        ys, xs = np.nonzero(green)
        lo, hi = corners.min(axis=0) - 80, corners.max(axis=0) + 80  # the marker moves between looks
        inside = (xs >= lo[0]) & (xs <= hi[0]) & (ys >= lo[1]) & (ys <= hi[1])
        assert inside.mean() > 0.6, (corners, xs.min(), xs.max(), ys.min(), ys.max())
        # The marker itself: black pixels where the green outline is, as many as its area.
        gx, gy = xs[inside], ys[inside]
        (ax, bx), (ay, by) = np.percentile(gx, (2, 98)), np.percentile(gy, (2, 98))
        box = view[int(ay) : int(by) + 1, int(ax) : int(bx) + 1]
        dark = int((box.max(axis=2) < 60).sum())
        area = cv2.contourArea(corners.astype(np.float32))
        assert dark > 0.4 * area, (dark, area, (ax, bx, ay, by))
        target = os.environ.get("POSE_DAEMON_SCREENSHOT")
        if target:
            shutil.copyfile(_save(png, tmp_path / "shot.png"), target)
    finally:
        browser.close()
    assert data["status"]["preview"]["max_fps"] == 5.0
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(20) == 0


def _save(png: bytes, path: Path) -> Path:
    path.write_bytes(png)
    return path
