"""The test metrics of one run as a table: per-class rows and the class mean.

:func:`format_metrics_table` is the fixed-width text that ``python -m src.train`` and ``python -m
src.eval`` print; :func:`format_metrics_markdown` is the Markdown of ``metrics.md`` (``src.eval``).

Which metric goes where is decided by :func:`metric_layout`, from the keys of ``metrics.json`` alone, so
a method that logs a metric of its own is shown without a change here. The order is fixed:

1. the headline metrics, :data:`TABLE_COLUMNS`, always (a metric the method does not have, such as a
   point regressor's log likelihood, reads ``n/a``);
2. after recalibration (docs/evaluation.md#recalibration): :data:`RECALIBRATED_COLUMNS`, then any other
   ``<metric>_calibrated`` key, when the run has them;
3. the method's own metrics: :data:`METHOD_COLUMNS` (``log_likelihood_exact`` of the families with a
   closed-form normaliser), then every key this module does not know, by name;
4. details, with ``details=True``: the coverage of the highest-density regions (``hdr_coverage_<mass>``, and
   after recalibration) as a per-class table of its own, then one line of the run's single numbers
   (:data:`RUN_NUMBERS`: loss, temperature, test images) and one of its timings (``*_seconds``), which never
   sit among the headline columns.

A class without any of a table's metrics has no row in it. The paper's tables, over many runs, are
:mod:`image2sphere.reporting.tables`; the table of a sweep, :mod:`image2sphere.reporting.sweep_table`, uses
the same layout.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

__all__ = [
    "CALIBRATED",
    "METHOD_COLUMNS",
    "RECALIBRATED_COLUMNS",
    "RUN_NUMBERS",
    "SECONDS",
    "TABLE_COLUMNS",
    "TIMINGS",
    "MetricLayout",
    "format_metrics_markdown",
    "format_metrics_table",
    "metric_layout",
]

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
# metrics that only some methods write; any key not known here is shown after these, titled by its name
METHOD_COLUMNS = (("log_likelihood_exact", "LL exact", "{:9.3f}"),)
# numbers of the whole run (no per-class value): one line under the tables
RUN_NUMBERS = (
    ("loss", "loss", "{:.3f}"),
    ("temperature", "temperature", "{:.3f}"),
    ("n_images", "test images", "{:.0f}"),
    ("skipped_images", "skipped images", "{:.0f}"),
)
# wall times, ``<part>_seconds``: the known ones in the order a run spends them, others after them by name
TIMINGS = ("train_seconds", "recalibration_seconds", "test_seconds")
CALIBRATED = "_calibrated"
SECONDS = "_seconds"
_COVERAGE = re.compile(r"hdr_coverage_(\d+)")
_GENERIC_FORMAT = "{:9.3f}"


@dataclass
class MetricLayout:
    """The columns of each part of a metrics table, ``(key, title, format)`` in their fixed order."""

    main: list[tuple[str, str, str]] = field(default_factory=list)
    coverage: list[tuple[str, str, str]] = field(default_factory=list)
    coverage_calibrated: list[tuple[str, str, str]] = field(default_factory=list)
    numbers: list[tuple[str, str, str]] = field(default_factory=list)
    timings: list[tuple[str, str, str]] = field(default_factory=list)


def _title(key: str) -> str:
    """The column title of a key: its own where known, ``<title> recal.`` for a recalibrated twin, else the key."""
    for columns in (TABLE_COLUMNS, RECALIBRATED_COLUMNS, METHOD_COLUMNS, RUN_NUMBERS):
        for k, title, _ in columns:
            if k == key:
                return title
    if key.endswith(CALIBRATED):
        base = key[: -len(CALIBRATED)]
        if base != _title(base):
            return f"{_title(base)} recal."
    return key


def _coverage_level(key: str) -> int | None:
    match = _COVERAGE.fullmatch(key.removesuffix(CALIBRATED))
    return int(match.group(1)) if match else None


def metric_layout(keys: Iterable[str]) -> MetricLayout:
    """Where each metric of ``keys`` (the keys of one or several ``metrics.json``; per-class keys
    ``<metric>/<class>`` count as their metric) is shown, in the module's fixed order."""
    present = {str(k).split("/", 1)[0] for k in keys}
    layout = MetricLayout(main=list(TABLE_COLUMNS))
    known = {k for columns in (TABLE_COLUMNS, RECALIBRATED_COLUMNS, METHOD_COLUMNS, RUN_NUMBERS) for k, _, _ in columns}
    layout.main += [c for c in RECALIBRATED_COLUMNS if c[0] in present]
    coverage, timings, twins, unknown = [], [], [], []
    for key in sorted(present - known):
        if _coverage_level(key) is not None:
            coverage.append(key)
        elif key.endswith(SECONDS):
            timings.append(key)
        elif key.endswith(CALIBRATED):
            twins.append(key)
        else:
            unknown.append(key)
    layout.main += [(k, _title(k), "{:11.3f}") for k in twins]
    layout.main += [c for c in METHOD_COLUMNS if c[0] in present]
    layout.main += [(k, k, _GENERIC_FORMAT) for k in unknown]
    for key in sorted(coverage, key=lambda k: (k.endswith(CALIBRATED), _coverage_level(k))):
        column = (key, f"{_coverage_level(key)}%", "{:6.3f}")
        (layout.coverage_calibrated if key.endswith(CALIBRATED) else layout.coverage).append(column)
    layout.numbers = [c for c in RUN_NUMBERS if c[0] in present]
    order = {k: i for i, k in enumerate(TIMINGS)}
    for key in sorted(timings, key=lambda k: (order.get(k, len(order)), k)):
        layout.timings.append((key, key.removesuffix(SECONDS), "{:.1f}"))
    return layout


def _width(title: str, fmt: str) -> int:
    return max(len(title), len(fmt.format(0.0)))


def _rows(metrics: dict[str, float], class_names: list[str], columns) -> Iterator[tuple[str, list[str | None]]]:
    """``(name, cells)`` of each class and the mean that has a metric: a column's value in its
    format, ``None`` where the metric is absent."""
    for name in [*class_names, "mean"]:
        key = "" if name == "mean" else f"/{name}"
        if any(metric + key in metrics for metric, _, _ in columns):
            values = [(metrics.get(metric + key), fmt) for metric, _, fmt in columns]
            yield name, [None if v is None else fmt.format(v) for v, fmt in values]


def _text_table(metrics: dict[str, float], class_names: list[str], columns) -> list[str]:
    widths = [_width(title, fmt) for _, title, fmt in columns]
    width = max([len(n) for n in class_names] + [len("mean"), len("class")])
    titles = [f"{title:>{w}}" for (_, title, _), w in zip(columns, widths, strict=True)]
    lines = [" ".join([f"{'class':<{width}}", *titles])]
    for name, cells in _rows(metrics, class_names, columns):
        shown = [f"{'n/a' if c is None else c:>{w}}" for c, w in zip(cells, widths, strict=True)]
        lines.append(" ".join([f"{name:<{width}}", *shown]))
    return lines


def _markdown_table(metrics: dict[str, float], class_names: list[str], columns) -> list[str]:
    lines = [
        "| class | " + " | ".join(title for _, title, _ in columns) + " |",
        "|---" * (len(columns) + 1) + "|",
    ]
    for name, cells in _rows(metrics, class_names, columns):
        lines.append(f"| {name} | " + " | ".join("n/a" if c is None else c.strip() for c in cells) + " |")
    return lines


COVERAGE_TITLE = "HDR coverage (fraction of the (image, rotation) pairs inside the highest-density region of each mass)"


def _detail_parts(metrics: dict[str, float], class_names: list[str], layout: MetricLayout, table) -> list[str]:
    """The details under the main table: the coverage tables (each after a title line), the run's numbers
    and its timings (one line each); ``table`` renders a per-class table's lines."""
    lines: list[str] = []
    for title, columns in ((COVERAGE_TITLE, layout.coverage), ("HDR coverage after recalibration",
                                                                layout.coverage_calibrated)):  # fmt: skip
        if columns:
            lines += ["", f"{title}:", *table(metrics, class_names, columns)]
    numbers = [f"{title} {fmt.format(metrics[key])}" for key, title, fmt in layout.numbers if key in metrics]
    timings = [f"{title} {fmt.format(metrics[key])}" for key, title, fmt in layout.timings if key in metrics]
    if numbers or timings:
        lines.append("")
    if numbers:
        lines.append(", ".join(numbers))
    if timings:
        lines.append("seconds: " + ", ".join(timings))
    return lines


def format_metrics_table(metrics: dict[str, float], class_names: list[str], details: bool = False) -> str:
    """Per-class rows and the class mean as a fixed-width text table (no trailing newline): the headline
    metrics, those after recalibration and the method's own (see the module). ``details``: then the HDR
    coverage tables and the lines of the run's numbers and timings, each part after a blank line."""
    layout = metric_layout(metrics)
    lines = _text_table(metrics, class_names, layout.main)
    if details:
        lines += _detail_parts(metrics, class_names, layout, _text_table)
    return "\n".join(lines)


def format_metrics_markdown(metrics: dict[str, float], class_names: list[str], details: bool = False) -> str:
    """Per-class rows and the class mean as a Markdown table, the columns of :func:`format_metrics_table`
    (and with ``details`` its further parts, the coverage as Markdown tables)."""
    layout = metric_layout(metrics)
    lines = _markdown_table(metrics, class_names, layout.main)
    if details:
        lines += _detail_parts(metrics, class_names, layout, _markdown_table)
    return "\n".join(lines) + "\n"
