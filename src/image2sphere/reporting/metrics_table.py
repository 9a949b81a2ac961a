"""The test metrics of one run as a table: per-class rows and the class mean.

:func:`format_metrics_table` is the fixed-width text that ``python -m src.train`` and ``python -m
src.eval`` print; :func:`format_metrics_markdown` is the Markdown of ``metrics.md`` (``src.eval``). Both
show every column of :data:`TABLE_COLUMNS`, and those of :data:`RECALIBRATED_COLUMNS` when the run
fitted a recalibration (docs/evaluation.md#recalibration); a metric the method does not have (a point
regressor's log likelihood, spread and calibration) reads ``n/a``. A class without any of the metrics has no row.
The paper's tables, over many runs, are :mod:`image2sphere.reporting.tables`.
"""

from __future__ import annotations

from collections.abc import Iterator

__all__ = ["RECALIBRATED_COLUMNS", "TABLE_COLUMNS", "format_metrics_markdown", "format_metrics_table"]

# (metric key in metrics.json, column title, number format of the text table)
TABLE_COLUMNS = (
    ("log_likelihood", "log lik.", "{:9.3f}"),
    ("spread_deg", "spread", "{:8.2f}"),
    ("calibration_ece", "ECE", "{:6.3f}"),
    ("acc15", "acc@15", "{:7.3f}"),
    ("acc30", "acc@30", "{:7.3f}"),
    ("median_error_deg", "med.err", "{:8.2f}"),
)
# after the recalibration's temperature: shown when the metrics have them
RECALIBRATED_COLUMNS = (
    ("log_likelihood_calibrated", "LL recal.", "{:10.3f}"),  # one wider than its title: two spaces before it
    ("calibration_ece_calibrated", "ECE recal.", "{:11.3f}"),
)


def _columns(metrics: dict[str, float]) -> tuple[tuple[str, str, str], ...]:
    recalibrated = tuple(c for c in RECALIBRATED_COLUMNS if c[0] in metrics)
    return TABLE_COLUMNS + recalibrated


def _rows(metrics: dict[str, float], class_names: list[str], columns) -> Iterator[tuple[str, list[str | None]]]:
    """``(name, cells)`` of each class and the mean that has a metric: a column's value in its
    format, ``None`` where the metric is absent."""
    for name in [*class_names, "mean"]:
        key = "" if name == "mean" else f"/{name}"
        if any(metric + key in metrics for metric, _, _ in columns):
            values = [(metrics.get(metric + key), fmt) for metric, _, fmt in columns]
            yield name, [None if v is None else fmt.format(v) for v, fmt in values]


def format_metrics_table(metrics: dict[str, float], class_names: list[str]) -> str:
    """Per-class rows and the class mean as a fixed-width text table (no trailing newline)."""
    columns = _columns(metrics)
    widths = [len(fmt.format(0.0)) for _, _, fmt in columns]
    width = max([len(n) for n in class_names] + [len("mean")])
    titles = [f"{title:>{w}}" for (_, title, _), w in zip(columns, widths, strict=True)]
    lines = [" ".join([f"{'class':<{width}}", *titles])]
    for name, cells in _rows(metrics, class_names, columns):
        shown = [f"{'n/a':>{w}}" if c is None else c for c, w in zip(cells, widths, strict=True)]
        lines.append(" ".join([f"{name:<{width}}", *shown]))
    return "\n".join(lines)


def format_metrics_markdown(metrics: dict[str, float], class_names: list[str]) -> str:
    """Per-class rows and the class mean as a Markdown table, the columns of :func:`format_metrics_table`."""
    columns = _columns(metrics)
    lines = [
        "| class | " + " | ".join(title for _, title, _ in columns) + " |",
        "|---" * (len(columns) + 1) + "|",
    ]
    for name, cells in _rows(metrics, class_names, columns):
        lines.append(f"| {name} | " + " | ".join("n/a" if c is None else c.strip() for c in cells) + " |")
    return "\n".join(lines) + "\n"
