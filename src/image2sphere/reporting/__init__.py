"""Tables of results: the paper's tables from finished runs (``python -m src.tables``: run discovery and
which runs count, the tables' layouts and published numbers in ``paper_tables.yaml``, Markdown, LaTeX and
figures), the table of any other sweep, one row per setting (:mod:`.sweep_table`), and the metrics table of one run
that ``src.train`` and ``src.eval`` print and write (:mod:`.metrics_table`)."""

from image2sphere.reporting.metrics_table import format_metrics_markdown, format_metrics_table
from image2sphere.reporting.runs import Run, UnfinishedRun, counted_runs, find_runs
from image2sphere.reporting.sweep_table import (
    SweepTable,
    build_sweep_table,
    is_sweep,
    sweep_header,
    sweep_lines,
    sweep_to_latex,
    sweep_to_markdown,
)
from image2sphere.reporting.tables import FilledTable, build_table, draw_figure, load_layouts, to_latex, to_markdown

__all__ = [
    "FilledTable",
    "Run",
    "SweepTable",
    "UnfinishedRun",
    "build_sweep_table",
    "build_table",
    "counted_runs",
    "draw_figure",
    "find_runs",
    "format_metrics_markdown",
    "format_metrics_table",
    "is_sweep",
    "load_layouts",
    "sweep_header",
    "sweep_lines",
    "sweep_to_latex",
    "sweep_to_markdown",
    "to_latex",
    "to_markdown",
]
