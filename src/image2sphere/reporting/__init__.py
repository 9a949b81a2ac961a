"""The paper's tables from finished runs (``python -m src.tables``): run discovery, the tables'
layouts and published numbers (``paper_tables.yaml``), Markdown, LaTeX and figures."""

from image2sphere.reporting.runs import Run, UnfinishedRun, find_runs
from image2sphere.reporting.tables import FilledTable, build_table, draw_figure, load_layouts, to_latex, to_markdown

__all__ = [
    "FilledTable",
    "Run",
    "UnfinishedRun",
    "build_table",
    "draw_figure",
    "find_runs",
    "load_layouts",
    "to_latex",
    "to_markdown",
]
