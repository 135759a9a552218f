"""The live viewer in a real headless Chromium: `beadsight live` on a video file, driven by
Playwright. Saves screenshots to artifacts/ (printed) for a person to look at."""

from __future__ import annotations

import re
import signal
from pathlib import Path

import numpy as np
import pytest
from helpers.browser import ARTIFACTS, CHROMIUM, CHROMIUM_ARGS, Beadsight
from helpers.live import live_argv, press_frames, tiny_model, write_video

from beadsight.live.recording.readings import open_readings

VIDEO_FPS = 30
VIDEO_FRAMES = 210  # 7 s: long enough to load the page and watch it update

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(not CHROMIUM.exists(), reason="chromium is not installed"),
]


def test_viewer_shows_live_readings_then_no_signal(tmp_path):
    from playwright import sync_api as playwright_api

    frames, _ = press_frames(presses=4, per_press=VIDEO_FRAMES // 4)
    video = write_video(tmp_path / "press.avi", frames, fps=VIDEO_FPS)
    checkpoint = tiny_model(scale_kpa=60.0).save(tmp_path / "tiny.pt")
    ARTIFACTS.mkdir(exist_ok=True)
    with playwright_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        more = ["--port", "0", "--record-dir", str(tmp_path)]
        live = Beadsight(*live_argv(checkpoint, video, *more, "--report-every", "1"))
        proc = live.proc
        try:
            url = live.wait_line(r"viewer: (http://\S+)", 60).group(1)
            page = browser.new_page(viewport={"width": 1400, "height": 900})
            page.goto(url)
            _check_live_page(page, tmp_path)
            page.wait_for_function("document.body.classList.contains('no-signal')", timeout=30_000)
            assert page.locator("#status-state").inner_text() == "ended"
            assert page.locator(".nosignal").first.is_visible()
            assert "NO SIGNAL" in page.locator(".nosignal").first.inner_text()
            assert "end of file" in page.locator("#status-message").inner_text() or "ended" in (
                page.locator("#status-message").inner_text()
            )
            shot = ARTIFACTS / "viewer-no-signal.png"
            page.screenshot(path=str(shot))
            print(f"screenshot: {shot}")
            page.close()
        finally:
            browser.close()
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=30)
            finally:
                proc.kill()
    seen = live.rest()
    assert proc.returncode == 0, seen
    assert any(line.startswith("final: ") for line in seen), seen


def _check_live_page(page, tmp_path: Path) -> None:
    page.wait_for_function(
        "document.getElementById('status-state').textContent === 'ok'", timeout=30_000
    )
    assert not page.locator(".nosignal").first.is_visible()
    # frames arrive and the force value changes over time
    seen = page.wait_for_function(
        """() => {
            const w = window, f = document.getElementById('force-value').textContent;
            w.forces = w.forces || new Set(); w.indices = w.indices || new Set();
            w.forces.add(f); w.indices.add(document.getElementById('frame-index').textContent);
            return w.forces.size >= 3 && w.indices.size >= 5 && [...w.forces];
        }""",
        polling=50,
        timeout=20_000,
    ).json_value()
    assert all(re.fullmatch(r"\d+\.\d\d", f) for f in set(seen) - {"–"}), seen
    # the sensor's measured rate: positive, at most the video's pace (60 fps); how far below
    # 30 Hz it is depends on the machine's load (9.4 Hz seen with three jobs on 2 cores)
    rate = float(page.locator("#rate").inner_text())
    assert 0 < rate < 60, rate
    assert float(page.locator("#latency-p50").inner_text()) > 0
    # the health chip shows a state from the sensor (no rest reference yet: unknown, or
    # ok once still rest frames were seen), with its message as the tooltip
    chip = page.locator("#health")
    assert chip.is_visible()
    assert page.locator("#health-state").inner_text() in ("unknown", "ok", "drifting")
    assert chip.get_attribute("title")
    # re-take rest button: the server answers that a new rest reference was asked for
    rest = page.locator("#rest-btn")
    assert rest.is_visible() and "rest reference" in rest.get_attribute("title")
    rest.click()
    page.wait_for_function(
        """() => { const b = document.getElementById('rest-btn');
             return b.textContent === 'Taking rest…' || b.title.includes('requested'); }""",
        timeout=10_000,
    )
    assert "failed" not in page.locator("#record-info").inner_text()
    # the images were drawn: the map canvas and the camera canvas are not blank
    for canvas in ("map", "frame", "colorbar", "trace"):
        lit = page.evaluate(
            """(id) => { const c = document.getElementById(id);
                 const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
                 let n = 0; for (let i = 0; i < d.length; i += 4) if (d[i] + d[i+1] + d[i+2] > 60) n++;
                 return n / (d.length / 4); }""",
            canvas,
        )
        assert lit > 0.01, (canvas, lit)
    # record button: record a second of readings to HDF5
    page.click("#record-btn")
    page.wait_for_function(
        "/ · [1-9]\\d* readings/.test(document.getElementById('record-info').textContent)",
        timeout=10_000,
    )
    assert page.locator("#record-btn").inner_text() == "Stop"
    shot = ARTIFACTS / "viewer.png"
    page.screenshot(path=str(shot))
    print(f"screenshot: {shot}")
    page.click("#record-btn")
    page.wait_for_function(
        "document.getElementById('record-btn').textContent === 'Record'", timeout=10_000
    )
    files = list(tmp_path.glob("beadsight-*.h5"))
    assert len(files) == 1, sorted(p.name for p in tmp_path.iterdir())
    with open_readings(files[0]) as rf:
        assert len(rf) >= 1
        assert np.all(np.diff(rf.timestamp_s) > 0)
