"""HTML reports: one self-contained page describing an evaluation, beside its files.

``beadsight demo``, ``beadsight evaluate --out DIR`` and calibration write their
``index.html`` with :func:`write_report` from a :class:`Report`:

* a title and a one-paragraph summary (what was evaluated, on what data, with which model);
* the metrics as an HTML table beside the paper's figures and the baselines, every value
  with a paper counterpart marked better or worse than the paper
  (:func:`beadsight.report.paper.compare_with_paper`);
* notes, then the figures (animation, plots), each with a caption saying what it shows and
  how to read it;
* tables of rows (the per-press metrics, worst first; the page runs no script, so the
  order is fixed: the same rows are a CSV file beside it, for sorting elsewhere);
* an optional model card, Markdown rendered by markdown-it-py, after the results and folded;
* links to the raw files (``metrics.json``, ``predictions.h5``, plots).

Every text is escaped; the model card is rendered with raw HTML disabled and only safe link
schemes, so a card cannot inject markup or script. Images and raw files stay files beside
the page, linked by relative paths; the page loads nothing else (no server, no network, no
external CSS, JS or fonts). The page layout and style are in ``page.html`` beside this
module.

:func:`evaluation_report` builds the :class:`Report` of a metrics dict returned by
:func:`beadsight.evaluation.evaluate.evaluate`; the demo adds its animation and notes.
"""

from __future__ import annotations

import datetime
import html
import importlib.resources
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from string import Template
from urllib.parse import quote

from beadsight import __version__
from beadsight.config import SensorGeometry
from beadsight.files import atomic_write_text
from beadsight.metrics import REGION_GRID
from beadsight.report.force_plots import force_error_caption, force_scatter_caption
from beadsight.report.paper import PAPER_METRICS, TABLE_ROWS, compare_with_paper
from beadsight.report.plots import (
    examples_caption,
    force_traces_caption,
    region_error_caption,
)
from beadsight.report.training import training_curve_caption

REPORT_FILE = "index.html"
TEMPLATE = "page.html"  # package file beside this module
MODEL_CARD_SUFFIX = ".md"  # a checkpoint's model card: the Markdown file of the same name
CARD_HEADING_OFFSET = 2  # a card's "#" becomes <h3>, under the page's <h2>


@dataclass(frozen=True)
class Figure:
    """A picture of the report: a file beside the page, a title and a caption."""

    file: str  # path relative to the report folder
    title: str
    caption: str  # what it shows and how to read it: axes, units, colour scale


@dataclass(frozen=True)
class Table:
    """A table of rows (dicts) under a title and a caption, in the order given."""

    id: str  # the HTML id of its section
    title: str
    caption: str  # what it shows and how to read it
    columns: Sequence[tuple[str, str, str]]  # (key, heading with unit, format)
    rows: Sequence[Mapping]


@dataclass(frozen=True)
class Link:
    """A raw file beside the page."""

    file: str  # path relative to the report folder
    description: str


@dataclass(frozen=True)
class Report:
    """Everything an evaluation report page shows, in order.

    metrics: this run's values by key (see ``rows``), or None for no table. paper: the
    paper's figures by key. baselines: {name: metrics dict}, each an extra column.
    rows: (key, label with unit, format) of the table, in order.
    """

    title: str
    summary: str
    metrics: Mapping | None = None
    paper: Mapping[str, float] = field(default_factory=lambda: dict(PAPER_METRICS))
    baselines: Mapping[str, Mapping] = field(default_factory=dict)
    rows: Sequence[tuple[str, str, str]] = TABLE_ROWS
    notes: Sequence[str] = ()
    figures: Sequence[Figure] = ()
    tables: Sequence[Table] = ()
    model_card: str | None = None  # Markdown
    model_card_title: str = "Model card"
    files: Sequence[Link] = ()


# --- rendering ----------------------------------------------------------------------
def _e(text: object) -> str:
    return html.escape(str(text), quote=True)


def _href(file: str) -> str:
    """A relative link to a file beside the page (each path part percent-encoded)."""
    return _e(quote(file, safe="/"))


def render_markdown(text: str, heading_offset: int = CARD_HEADING_OFFSET) -> str:
    """Markdown -> HTML with raw HTML disabled: tags in ``text`` come out as text, links
    with unsafe schemes (javascript:, data:, ...) are not made, images are not loaded.
    Headings move ``heading_offset`` levels down (a card's ``#`` under the page's ``h2``)."""
    from markdown_it import MarkdownIt

    md = MarkdownIt("commonmark", {"html": False}).enable("table").disable("image")
    tokens = md.parse(text)
    for token in tokens:
        if token.type in ("heading_open", "heading_close"):
            token.tag = f"h{min(int(token.tag[1:]) + heading_offset, 6)}"
    return md.renderer.render(tokens, md.options, {})


def _cell(value: object, fmt: str) -> str:
    if value is None:
        return "n/a"
    return fmt.format(int(value) if fmt == "{:d}" else float(value))


def _value_cell(key: str, value: object, fmt: str, paper: Mapping, css: str) -> str:
    text = _cell(value, fmt)
    verdict = None
    if key in paper and value is not None:
        verdict = compare_with_paper(key, float(value), fmt)
    if verdict is None:
        return f'<td class="{css}">{_e(text)}</td>'
    tip = f"paper: {_cell(paper[key], fmt)}"
    mark = {"better": "better", "worse": "worse", "same": "= paper"}[verdict]
    return (
        f'<td class="{css} {verdict}" title="{_e(tip)}">{_e(text)}'
        f'<span class="mark">{_e(mark)}</span></td>'
    )


def metrics_table(report: Report) -> str:
    """The metrics as an HTML table: this run, the paper, the baselines (one column each)."""
    paper = report.paper
    columns: list[tuple[str, Mapping, str]] = [("this run", report.metrics or {}, "run")]
    columns.append(("paper", paper, "paper"))
    columns += [(f"baseline: {name}", m, "baseline") for name, m in report.baselines.items()]
    head = "".join(f'<th scope="col">{_e(name)}</th>' for name, _, _ in columns)
    body = []
    for key, label, fmt in report.rows:
        cells = []
        for _, values, css in columns:
            if values is paper:
                text = _cell(paper[key], fmt) if key in paper else "–"
                cells.append(f'<td class="paper">{_e(text)}</td>')
            else:
                cells.append(_value_cell(key, values.get(key), fmt, paper, css))
        body.append(f'<tr><th scope="row">{_e(label)}</th>{"".join(cells)}</tr>')
    caption = (
        "Each value with a figure in the paper is marked better or worse than it: lower is "
        "better for the errors, higher for contact IoU. n/a: not measurable on this data "
        "(e.g. no frame with enough force)."
    )
    return (
        f'<table class="metrics"><caption>{_e(caption)}</caption>'
        f'<thead><tr><th scope="col">metric</th>{head}</tr></thead>'
        f"<tbody>{''.join(body)}</tbody></table>"
    )


def _figure(n: int, fig: Figure) -> str:
    return (
        f'<figure id="figure-{n}"><a href="{_href(fig.file)}">'
        f'<img src="{_href(fig.file)}" alt="{_e(fig.title)}"></a>'
        f"<figcaption><strong>Figure {n}. {_e(fig.title)}.</strong> {_e(fig.caption)}"
        "</figcaption></figure>"
    )


def render_table(table: Table) -> str:
    """A :class:`Table` as an HTML table, in a box that scrolls when it is long."""
    head = "".join(
        f'<th scope="col" data-key="{_e(key)}">{_e(label)}</th>' for key, label, _ in table.columns
    )
    body = []
    for row in table.rows:
        cells = "".join(
            f'<td data-key="{_e(key)}">{_e(_cell(row.get(key), fmt))}</td>'
            for key, _, fmt in table.columns
        )
        body.append(f"<tr>{cells}</tr>")
    return (
        f'<h2 id="{_e(table.id)}">{_e(table.title)}</h2>'
        f'<div class="scroll"><table class="rows" id="{_e(table.id)}-table">'
        f"<caption>{_e(table.caption)}</caption><thead><tr>{head}</tr></thead>"
        f"<tbody>{''.join(body)}</tbody></table></div>"
    )


def _size(path: Path) -> str:
    if not path.is_file():
        return ""
    size = float(path.stat().st_size)
    for unit in ("B", "kB", "MB", "GB"):
        if size < 1000 or unit == "GB":
            return f"{size:.0f} {unit}" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1000
    return ""  # pragma: no cover


def _files(links: Sequence[Link], folder: Path | None) -> str:
    items = []
    for link in links:
        size = _size(folder / link.file) if folder is not None else ""
        size_html = f' <span class="size">({_e(size)})</span>' if size else ""
        items.append(
            f'<li><a href="{_href(link.file)}">{_e(link.file)}</a>{size_html}: '
            f"{_e(link.description)}</li>"
        )
    return f'<ul class="files">{"".join(items)}</ul>'


def render_report(report: Report, folder: Path | None = None) -> str:
    """The report page as HTML text; ``folder`` (where it will be written) gives file sizes."""
    parts = [
        '<p class="kicker">beadsight report</p>',
        f"<h1>{_e(report.title)}</h1>",
        f'<p class="summary">{_e(report.summary)}</p>',
    ]
    if report.metrics is not None:
        parts += ['<h2 id="results">Results</h2>', metrics_table(report)]
    if report.notes:
        parts.append(f'<ul class="notes">{"".join(f"<li>{_e(n)}</li>" for n in report.notes)}</ul>')
    if report.figures:
        parts.append('<h2 id="figures">Figures</h2>')
        parts += [_figure(n, fig) for n, fig in enumerate(report.figures, start=1)]
    parts += [render_table(table) for table in report.tables]
    if report.model_card:
        parts += [
            '<h2 id="model">The model</h2>',
            f"<details><summary>{_e(report.model_card_title)}</summary>"
            f'<div class="card">{render_markdown(report.model_card)}</div></details>',
        ]
    if report.files:
        parts += ['<h2 id="files">Files</h2>', _files(report.files, folder)]
    when = datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    template = importlib.resources.files("beadsight.report").joinpath(TEMPLATE).read_text()
    return Template(template).substitute(
        title=_e(report.title),
        generator=_e(f"beadsight {__version__}"),
        content="\n".join(parts),
        footer=_e(f"Written by beadsight {__version__} on {when}."),
    )


def write_report(report: Report, folder: str | Path, name: str = REPORT_FILE) -> Path:
    """Write the report page to ``folder/name`` atomically (a full disk: WriteError)."""
    folder = Path(folder)
    return atomic_write_text(folder / name, render_report(report, folder))


# --- evaluation reports -------------------------------------------------------------
def model_card_for(checkpoint: str | Path) -> str | None:
    """The model card of a checkpoint: the Markdown file of the same name beside it
    (``sim_model.md`` for ``sim_model.pt``), or None."""
    path = Path(checkpoint).with_suffix(MODEL_CARD_SUFFIX)
    try:
        return path.read_text(encoding="utf-8") if path.is_file() else None
    except (OSError, UnicodeDecodeError):
        return None


def evaluation_figures(
    files: Mapping[str, str], metrics: Mapping, geometry: SensorGeometry | None = None
) -> list[Figure]:
    """Figures of the evaluation plots named in ``files`` ({role: file name}); ``geometry``:
    the sensor's (for the region cells' size in mm; default: the reference sensor)."""
    grid = len(metrics.get("region_mae_kpa") or []) or REGION_GRID
    cell_mm = (geometry or SensorGeometry()).sensor_size_mm / grid
    known = {
        "examples": ("True and predicted pressure maps", examples_caption()),
        "force_traces": ("Total force over time", force_traces_caption()),
        "force_scatter": ("Predicted against true force", force_scatter_caption()),
        "force_error": ("Force error against force", force_error_caption()),
        "region_error": ("Error by press location", region_error_caption(grid, cell_mm)),
        "training_curve": ("Learning curve of the training run", training_curve_caption()),
    }
    return [Figure(files[k], title, text) for k, (title, text) in known.items() if k in files]


FILE_DESCRIPTIONS = {
    "metrics": "the metrics, their definitions, counts and what was evaluated (strict JSON)",
    "predictions": "per-frame predicted and true maps (kPa), forces (N), centres of pressure "
    "(mm) and frame indices (HDF5)",
    "examples": "example maps (PNG)",
    "region_error": "error by press location (PNG)",
    "force_traces": "force over time (PNG)",
    "force_scatter": "predicted against true force (PNG)",
    "force_error": "force error against force (PNG; the numbers: force_error_by_force in "
    "metrics.json)",
    "training_curve": "the learning curve of the checkpoint's training run (PNG)",
    "presses": "the metrics of each press, worst first (CSV; also per_press in metrics.json)",
}
PRESS_TABLE_COLUMNS = (
    ("press", "press", "{:d}"),
    ("frames", "frames", "{:d}"),
    ("x_mm", "x (mm)", "{:.1f}"),
    ("y_mm", "y (mm)", "{:.1f}"),
    ("peak_force_n", "peak true force (N)", "{:.2f}"),
    ("force_error_pct", "force error (%)", "{:.1f}"),
    ("cop_error_mm", "CoP error (mm)", "{:.2f}"),
    ("iou", "contact IoU", "{:.3f}"),
    ("mae_kpa", "MAE (kPa)", "{:.3f}"),
)


def press_tables(metrics: Mapping) -> list[Table]:
    """The per-press table of an evaluation's metrics (its ``per_press`` rows), or none."""
    rows = metrics.get("per_press")
    if not rows:
        return []
    caption = (
        "The table's metrics on each press's evaluated frames, worst first (highest total-force "
        "error). x, y: where the press was (mm, printer frame); CoP error and IoU count frames "
        "with at least 2 N of true force (n/a: none). To sort by another column, open "
        "presses.csv (the same rows; also per_press in metrics.json) in a spreadsheet."
    )
    return [Table("presses", "Per press", caption, PRESS_TABLE_COLUMNS, rows)]


def evaluation_links(
    files: Mapping[str, str], descriptions: Mapping[str, str] | None = None
) -> list[Link]:
    """Links to the raw files ``files`` ({role: file name}), the report page itself left out;
    ``descriptions`` ({role: text}) add to or replace :data:`FILE_DESCRIPTIONS`."""
    known = {**FILE_DESCRIPTIONS, **(descriptions or {})}
    return [
        Link(name, known.get(role, role)) for role, name in files.items() if name != REPORT_FILE
    ]


def _split_text(metrics: Mapping) -> str:
    split, source = metrics.get("split", "?"), metrics.get("split_source", "")
    if split == "all":
        return "every press"
    how = {
        "checkpoint": "as stored in the checkpoint",
        "recomputed": "recomputed",
        "given": "presses kept out of training",
    }.get(source, source)
    return f"the {split} split ({how})" if how else f"the {split} split"


def evaluation_summary(metrics: Mapping) -> str:
    """One paragraph: which model, on what data, how many frames (and the coverage)."""
    span = metrics.get("span")
    model = f"The model {Path(str(metrics.get('checkpoint', '?'))).name}"
    if span is not None:
        model += f" ({metrics.get('image_size', '?')} px frames, windows of {span} frames)"
    frames = metrics.get("frames", 0)
    presses = metrics.get("presses", 0)
    text = (
        f"{model} was evaluated on {_split_text(metrics)} of the dataset "
        f"{metrics.get('dataset', '?')}: {frames} frames of {presses} "
        f"press{'es' if presses != 1 else ''}"
    )
    if metrics.get("coverage") is not None:
        text += f", {100 * float(metrics['coverage']):.1f} % of its valid frames"
    if metrics.get("max_frames"):
        text += f" (at most {metrics['max_frames']}, spread evenly"
        if metrics.get("window_coverage") is not None:
            text += f" over the {100 * float(metrics['window_coverage']):.1f} % with a full window"
        text += ")"
    text += f", on {metrics.get('device', '?')}. Checkpoint: {metrics.get('checkpoint', '?')}."
    if metrics.get("baselines"):
        text += (
            " Baselines: "
            + str(metrics.get("baselines_note", ", ".join(metrics["baselines"])))
            + "."
        )
    return text


def evaluation_report(
    metrics: Mapping, title: str = "Evaluation", geometry: SensorGeometry | None = None
) -> Report:
    """The :class:`Report` of an evaluation's metrics dict (with its ``files``); the model
    card is the checkpoint's (:func:`model_card_for`)."""
    files = dict(metrics.get("files", {}))
    checkpoint = metrics.get("checkpoint")
    card = model_card_for(checkpoint) if checkpoint else None
    return Report(
        title=f"{title}: {Path(str(checkpoint)).name}" if checkpoint else title,
        summary=evaluation_summary(metrics),
        metrics=metrics,
        baselines=metrics.get("baselines") or {},
        figures=evaluation_figures(files, metrics, geometry),
        tables=press_tables(metrics),
        model_card=card,
        model_card_title=f"Model card ({Path(str(checkpoint)).with_suffix(MODEL_CARD_SUFFIX).name})",
        files=evaluation_links(files),
    )
