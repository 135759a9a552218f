"""The HTML report builder: escaping, hostile model cards, better/worse marks, self-contained
pages, and the report ``beadsight evaluate --out`` writes. The page is checked with the
standard library's HTML parser, not with the code that wrote it."""

from __future__ import annotations

import json
from html.parser import HTMLParser

import pytest

from beadsight.cli import main
from beadsight.evaluation.report import Figure, Link, Report, render_report, write_report
from beadsight.files import WriteError
from beadsight.metrics import PAPER_METRICS, compare_with_paper

HOSTILE_CARD = """# Model <b>card</b>

<script>alert("card")</script>

<img src=x onerror="alert('img')">

[click me](javascript:alert('link')) and [data](data:text/html;base64,PHNjcmlwdD4=)

![remote](https://example.com/track.png)

| a | b |
|---|---|
| 1 | 2 |
"""


class Page(HTMLParser):
    """Every start tag with its attributes, and the text inside given elements."""

    def __init__(self, text: str):
        super().__init__()
        self.tags: list[tuple[str, dict]] = []
        self._open: list[str] = []
        self.text: dict[str, list[str]] = {}
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))
        self._open.append(tag)

    def handle_endtag(self, tag):
        if tag in self._open:
            while self._open.pop() != tag:
                pass

    def handle_data(self, data):
        for tag in set(self._open):
            self.text.setdefault(tag, []).append(data)

    def all(self, tag: str) -> list[dict]:
        return [attrs for t, attrs in self.tags if t == tag]


def _report(**changes) -> Report:
    fields = dict(
        title="Eval <script>alert('title')</script>",
        summary="Model & data <i>summary</i>",
        metrics={
            "mae_kpa": 0.5,
            "force_error_pct": 11.9,
            "cop_error_mm": None,
            "iou": 0.5,
            "worst_region_mae_kpa": 2.0,
            "frames": 12,
        },
        baselines={"zero": {"mae_kpa": 3.0, "iou": 0.0, "frames": 12}},
        notes=["a <note>"],
        figures=[Figure("plots/a b.png", "A <figure>", "x in mm <b>bold</b>")],
        model_card=HOSTILE_CARD,
        files=[Link("metrics.json", "the <metrics>")],
    )
    fields.update(changes)
    return Report(**fields)


def assert_safe(page: Page) -> None:
    assert not page.all("script") and not page.all("link") and not page.all("iframe")
    for tag, attrs in page.tags:
        assert not any(name.startswith("on") for name in attrs), (tag, attrs)
        # what loads (src) is a file beside the page; links may point out, but run nothing
        assert ":" not in attrs.get("src", ""), (tag, attrs)
        assert not attrs.get("href", "").lower().startswith(("javascript:", "data:")), attrs


def test_everything_is_escaped_and_the_card_cannot_inject():
    text = render_report(_report())
    page = Page(text)
    assert_safe(page)
    assert "<script>alert" not in text and "<b>bold</b>" not in text
    assert "".join(page.text["title"]) == "Eval <script>alert('title')</script>"
    assert "Model & data <i>summary</i>" in "".join(page.text["p"])
    # the card's raw HTML shows as text; its Markdown table and heading are rendered
    card = "".join(page.text["details"])
    assert '<script>alert("card")</script>' in card and "onerror" in card
    assert len(page.all("h1")) == 1 and len(page.all("h3")) == 1  # the card's "#" is an h3
    assert len(page.all("table")) == 2
    # only the figure's image is loaded, from a file beside the page
    assert [img["src"] for img in page.all("img")] == ["plots/a%20b.png"]
    assert "click me" in card and not any("javascript" in a.get("href", "") for a in page.all("a"))


def test_the_card_is_folded_after_the_results():
    text = render_report(_report())
    page = Page(text)
    details = page.all("details")
    assert len(details) == 1 and "open" not in details[0]
    assert text.index('class="metrics"') < text.index("<figure") < text.index("<details>")


def test_metrics_are_marked_against_the_paper():
    page = Page(render_report(_report()))
    cells = page.all("td")
    verdicts = [c["class"].split()[-1] for c in cells if c.get("class", "").startswith("run")]
    # mae 0.5 < 0.79, force 11.9 = 11.9, cop n/a, iou 0.5 < 0.81, worst region 2.0 > 1.05
    assert verdicts == ["better", "same", "run", "worse", "worse", "run"]
    assert "n/a" in "".join(page.text["td"])
    zero = [c["class"] for c in cells if c.get("class", "").startswith("baseline")]
    assert zero[0] == "baseline worse" and zero[3] == "baseline worse"
    assert (
        compare_with_paper("iou", 0.9) == "better" and compare_with_paper("mae_kpa", 0.9) == "worse"
    )
    assert compare_with_paper("frames", 3) is None and compare_with_paper("iou", None) is None
    assert set(PAPER_METRICS) <= {
        "mae_kpa",
        "force_error_pct",
        "cop_error_mm",
        "iou",
        "worst_region_mae_kpa",
    }


def test_a_report_without_metrics_or_card():
    text = render_report(Report(title="Calibration", summary="s", figures=[]))
    page = Page(text)
    assert_safe(page)
    assert not page.all("table") and not page.all("details") and not page.all("img")


def test_write_report_on_a_full_disk(full_disk):
    with open(full_disk / "filler", "wb", buffering=0) as f, pytest.raises(OSError):
        while True:
            f.write(b"\0" * 4096)
    with pytest.raises(WriteError, match=r"index\.html.*disk full"):
        write_report(_report(), full_disk)
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler"]


def test_evaluate_writes_the_report(make_dataset, tiny_model, tmp_path):
    data = make_dataset()
    checkpoint = tiny_model.save(tmp_path / "tiny.pt")
    (tmp_path / "tiny.md").write_text(HOSTILE_CARD)  # the checkpoint's model card
    out = tmp_path / "eval"
    argv = [
        "evaluate",
        "--checkpoint",
        str(checkpoint),
        "--data",
        str(data),
        "--split",
        "all",
        "--out",
        str(out),
        "--device",
        "cpu",
        "--max-frames",
        "30",
        "--baselines",
        "--no-progress",
    ]
    assert main(argv) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["files"]["report"] == "index.html"
    text = (out / "index.html").read_text()
    page = Page(text)
    assert_safe(page)
    assert "tiny.pt" in "".join(page.text["h1"])
    summary = "".join(page.text["p"])
    assert str(data) in summary and "30 frames of 6 presses" in summary
    heads = [h.strip() for h in page.text["th"]]
    assert heads[:5] == ["metric", "this run", "paper", "baseline: zero", "baseline: mean_gt"]
    assert [img["src"] for img in page.all("img")] == [
        "examples.png",
        "force_traces.png",
        "region_error.png",
    ]
    captions = "".join(page.text["figcaption"])
    assert "kPa" in captions and "x (mm" in captions and "(N" in captions
    links = {a["href"] for a in page.all("a")}
    assert {"metrics.json", "predictions.h5", "examples.png"} <= links
    assert all((out / href).is_file() for href in links if ":" not in href)  # card: https
    assert len(page.all("details")) == 1
