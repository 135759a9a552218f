"""The paper's figures, and the tables that set a run's metrics beside them.

BeadSight, George et al. 2024, table of results: :data:`PAPER_METRICS`; the metrics are
defined in :mod:`beadsight.metrics`.
"""

from __future__ import annotations

PAPER_METRICS: dict[str, float] = {
    "mae_kpa": 0.79,
    "force_error_pct": 11.9,
    "cop_error_mm": 1.18,
    "iou": 0.81,
    "worst_region_mae_kpa": 1.05,
}
HIGHER_IS_BETTER = frozenset({"iou"})  # every other paper metric is an error: lower is better


TABLE_ROWS = (  # (metric key, label with unit, format) of the metrics tables
    ("mae_kpa", "pressure MAE (kPa)", "{:.3f}"),
    ("force_error_pct", "total-force error (%)", "{:.1f}"),
    ("cop_error_mm", "centre of pressure (mm)", "{:.2f}"),
    ("iou", "contact IoU (0..1)", "{:.3f}"),
    ("worst_region_mae_kpa", "worst 4x4 region MAE (kPa)", "{:.3f}"),
    ("frames", "frames", "{:d}"),
)


def format_metrics_table(metrics: dict, baselines: dict[str, dict] | None = None) -> str:
    """A plain-text table: this run beside the paper's figures (and baselines, if given).

    metrics: a result dict (keys as in :meth:`MetricsAccumulator.result`).
    baselines: optional {name: metrics dict}, each shown as an extra column.
    Missing values show as "n/a".
    """
    columns = [("this run", metrics), ("paper", PAPER_METRICS)]
    columns += [(f"baseline: {name}", m) for name, m in (baselines or {}).items()]

    def cell(m: dict, key: str, fmt: str) -> str:
        value = m.get(key)
        if value is None:
            return "n/a" if m is not PAPER_METRICS else "-"
        return fmt.format(int(value) if fmt == "{:d}" else float(value))

    rows = [["metric", *(name for name, _ in columns)]]
    rows += [[label, *(cell(m, key, fmt) for _, m in columns)] for key, label, fmt in TABLE_ROWS]
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = []
    for n, row in enumerate(rows):
        first = row[0].ljust(widths[0])
        rest = [v.rjust(w) for v, w in zip(row[1:], widths[1:], strict=True)]
        lines.append("  ".join([first, *rest]))
        if n == 0:
            lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines)


def compare_with_paper(key: str, value: float | None, fmt: str = "{:.3g}") -> str | None:
    """ "better", "worse" or "same" than the paper's figure for metric ``key``, as shown
    with ``fmt`` (values that print alike are the same); None if either is missing."""
    paper = PAPER_METRICS.get(key)
    if value is None or paper is None:
        return None
    ours, theirs = float(fmt.format(float(value))), float(fmt.format(float(paper)))
    if ours == theirs:
        return "same"
    higher = key in HIGHER_IS_BETTER
    return "better" if (ours > theirs) == higher else "worse"
