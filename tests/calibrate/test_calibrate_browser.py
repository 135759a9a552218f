"""The calibration report in a real headless Chromium, opened from disk: the metrics table
beside the paper and the other candidates, every image and caption, the raw-file links,
nothing loaded from outside the folder. Saves artifacts/report-calibrate.png."""

from __future__ import annotations

import pytest
from helpers.browser import ARTIFACTS, CHROMIUM, CHROMIUM_ARGS
from helpers.train import one_torch_thread  # noqa: F401  (an autouse fixture)

from beadsight.calibrate.config import CalibrateConfig
from beadsight.calibrate.report import CANDIDATE_NAMES
from beadsight.calibrate.run import calibrate

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(not CHROMIUM.exists(), reason="chromium is not installed"),
]
FIGURES = [
    "examples.png",
    "force_traces.png",
    "force_scatter.png",
    "force_error.png",
    "region_error.png",
    "training_curve.png",  # only where a fine-tuning was kept (it validates 2+ times)
    "learning_curve.png",
]


def test_calibration_report_in_chromium(make_dataset, tiny_model, tmp_path):
    from playwright import sync_api

    base = tiny_model.save(tmp_path / "base.pt")
    out = tmp_path / "cal"
    data = make_dataset(presses=6)
    config = CalibrateConfig(
        data=str(data), out=str(out), base=str(base), budget_min=0.3, progress=False
    )
    metrics = calibrate(config)
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1200, "height": 900})
        requests, errors = [], []
        page.on("request", lambda r: requests.append(r.url))
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto((out / "report.html").as_uri(), wait_until="load")
        assert page.locator("main > h1").inner_text().startswith("Calibration: tiny.h5")
        summary = page.locator("p.summary").inner_text()
        assert "presses were used" in summary and "Kept: " in summary
        heads = page.locator("table.metrics thead th").all_inner_texts()
        others = [
            f"baseline: {CANDIDATE_NAMES[n]}"
            for n, c in metrics["candidates"].items()
            if c["test"] and n != metrics["chosen"]
        ]
        assert heads == ["metric", "this run", "paper", *others]
        notes = page.locator("body").inner_text()
        assert all(f"Candidate {CANDIDATE_NAMES[n]}" in notes for n in metrics["candidates"])
        tuned = metrics["chosen"] in ("decoder", "all", "scratch")
        figures = [f for f in FIGURES if tuned or f != "training_curve.png"]
        images = page.locator("figure img")
        assert [images.nth(i).get_attribute("src") for i in range(images.count())] == figures
        sizes = page.evaluate("[...document.images].map(i => [i.complete, i.naturalWidth])")
        assert all(done and w > 0 for done, w in sizes), sizes
        captions = page.locator("figure figcaption").all_inner_texts()
        assert len(captions) == len(figures) and all(len(c) > 150 for c in captions)
        if tuned:
            assert "optimizer step" in captions[figures.index("training_curve.png")]
        # the test presses, one row each, worst force error first
        rows = page.locator("table.rows tbody tr")
        assert rows.count() == len((out / "presses.csv").read_text().splitlines()) - 1 >= 1
        links = page.locator("ul.files a").evaluate_all("as => as.map(a => a.getAttribute('href'))")
        assert {"metrics.json", "model.pt", "predictions.h5"} <= set(links)
        assert all((out / href).is_file() for href in links), links
        assert all(url.startswith(out.as_uri()) for url in requests), requests
        assert errors == []
        ARTIFACTS.mkdir(exist_ok=True)
        shot = ARTIFACTS / "report-calibrate.png"
        page.screenshot(path=str(shot), full_page=True)
        print(f"screenshot: {shot}")
        browser.close()
