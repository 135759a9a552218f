"""The demo and evaluate reports in a real headless Chromium, opened from disk (file://):
the metrics table, every image loaded, every caption, the folded model card, and no request
that leaves the report folder. Saves full-page screenshots to artifacts/ (printed)."""

from __future__ import annotations

import shutil

import pytest
from helpers.browser import ARTIFACTS, CHROMIUM, CHROMIUM_ARGS

from beadsight.assets import shipped_model_path
from beadsight.cli import main

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(not CHROMIUM.exists(), reason="chromium is not installed"),
]

PAPER_ROWS = (
    "pressure MAE (kPa)",
    "total-force error (%)",
    "centre of pressure (mm)",
    "contact IoU (0..1)",
    "worst 4x4 region MAE (kPa)",
)
EVALUATION_FIGURES = [
    "examples.png",
    "force_traces.png",
    "force_scatter.png",
    "force_error.png",
    "region_error.png",
]
HOW_TO_READ = {  # a figure's caption says how to read it
    "force_scatter.png": "y = x",
    "force_error.png": "n above each bar",
    "region_error.png": "not an error of 0",
}
PRESS_HEADINGS = [
    "press",
    "frames",
    "x (mm)",
    "y (mm)",
    "peak true force (N)",
    "force error (%)",
    "CoP error (mm)",
    "contact IoU",
    "MAE (kPa)",
]


@pytest.fixture(scope="module")
def shipped(tmp_path_factory):
    """The shipped model and its card, copied (a checkpoint with a card beside it)."""
    path = shipped_model_path()
    folder = tmp_path_factory.mktemp("model")
    shutil.copy(path, folder / "sim_model.pt")
    shutil.copy(path.with_suffix(".md"), folder / "sim_model.md")
    return folder / "sim_model.pt"


@pytest.fixture(scope="module")
def reports(shipped, tmp_path_factory):
    """{"demo": folder, "evaluate": folder}: the demo, then evaluate on the demo's data."""
    root = tmp_path_factory.mktemp("reports")
    demo = root / "demo"
    argv = [
        "demo",
        "--checkpoint",
        str(shipped),
        "--out",
        str(demo),
        "--presses",
        "3",
        "--max-frames",
        "36",  # about a dozen frames a press: each press has its row
        "--animation-frames",
        "6",
        "--device",
        "cpu",
        "--no-progress",
    ]
    assert main(argv) == 0
    evaluation = root / "evaluate"
    argv = [
        "evaluate",
        "--checkpoint",
        str(shipped),
        "--data",
        str(demo / "heldout.h5"),
        "--split",
        "all",
        "--out",
        str(evaluation),
        "--max-frames",
        "60",
        "--baselines",
        "--device",
        "cpu",
        "--no-progress",
    ]
    assert main(argv) == 0
    return {"demo": demo, "evaluate": evaluation}


@pytest.fixture(scope="module")
def browser():
    from playwright import sync_api

    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        yield browser
        browser.close()


@pytest.mark.parametrize(
    "kind, figures",
    [
        ("demo", ["animation.gif", *EVALUATION_FIGURES]),
        ("evaluate", EVALUATION_FIGURES),
    ],
)
def test_report_in_chromium(reports, browser, kind, figures):
    folder = reports[kind]
    page = browser.new_page(viewport={"width": 1200, "height": 900})
    requests, errors = [], []
    page.on("request", lambda r: requests.append(r.url))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto((folder / "index.html").as_uri(), wait_until="load")

    assert page.title() and page.locator("main > h1").inner_text()
    assert len(page.locator("p.summary").inner_text()) > 100
    # the metrics table: the paper's rows, this run beside the paper and both baselines
    table = page.locator("table.metrics")
    heads = table.locator("thead th").all_inner_texts()
    assert heads == ["metric", "this run", "paper", "baseline: zero", "baseline: mean_gt"]
    rows = table.locator("tbody th").all_inner_texts()
    assert list(PAPER_ROWS) == rows[: len(PAPER_ROWS)]
    marks = table.locator("td.run .mark").all_inner_texts()
    assert len(marks) == len(PAPER_ROWS) and set(marks) <= {"better", "worse", "= paper"}
    # every image is loaded from the folder, and every figure has its caption
    images = page.locator("figure img")
    assert [images.nth(i).get_attribute("src") for i in range(images.count())] == figures
    sizes = page.evaluate(
        "[...document.images].map(i => [i.complete, i.naturalWidth, i.naturalHeight])"
    )
    assert all(done and w > 0 and h > 0 for done, w, h in sizes), sizes
    captions = page.locator("figure figcaption").all_inner_texts()
    assert len(captions) == len(figures)
    assert all(text.startswith("Figure ") and len(text) > 150 for text in captions), captions
    assert all("kPa" in text or "(N" in text for text in captions)
    for file, words in HOW_TO_READ.items():
        assert words in captions[figures.index(file)], (file, captions[figures.index(file)])
    # the per-press table: every press, worst force error first, the same rows as the CSV
    presses = page.locator("table.rows")
    assert presses.locator("thead th").all_inner_texts() == PRESS_HEADINGS
    assert "worst first" in presses.locator("caption").inner_text()
    rows = presses.locator("tbody tr")
    csv_rows = (folder / "presses.csv").read_text().splitlines()[1:]
    assert rows.count() == len(csv_rows) == 3
    cells = presses.locator('td[data-key="force_error_pct"]').all_inner_texts()
    force_errors = [float(t) for t in cells]
    assert force_errors == sorted(force_errors, reverse=True)
    first = rows.nth(0).locator("td").all_inner_texts()
    assert first[0] == csv_rows[0].split(",")[0]  # the same press first
    # the model card: after the figures, folded, and rendered from Markdown when opened
    card = page.locator("details")
    assert card.count() == 1 and not card.evaluate("d => d.open")
    assert not page.locator("details .card h3").is_visible()
    page.screenshot(path=str(_shot(kind)), full_page=True)
    page.click("details > summary")
    assert page.locator("details .card h3").is_visible()
    assert page.locator("details .card pre code").count() > 0  # the card's code blocks
    # raw files are linked, and exist
    links = page.locator("ul.files a").evaluate_all("as => as.map(a => a.getAttribute('href'))")
    assert {"metrics.json", "predictions.h5"} <= set(links)
    assert all((folder / href).is_file() for href in links)
    # nothing was loaded from outside the report folder, and nothing failed
    assert requests and all(url.startswith(folder.as_uri()) for url in requests), requests
    assert errors == []
    page.close()


def _shot(kind: str):
    ARTIFACTS.mkdir(exist_ok=True)
    path = ARTIFACTS / f"report-{kind}.png"
    print(f"screenshot: {path}")
    return path
