"""The paper's tables from finished runs: our mean +- std over seeds beside the published numbers.

A table's layout and the paper's numbers are data (``paper_tables.yaml`` next to this file, read by
:func:`load_layouts`); :func:`build_table` fills a layout from runs (:mod:`.runs`), and
:func:`to_markdown`, :func:`to_latex` and :func:`draw_figure` write it.

Rules
-----
* A cell's runs are those that match the table's, the row's and the column's ``match``. Their
  values are averaged; the spread is the sample standard deviation (``n - 1``) over the runs (the
  seeds), shown when there are two or more.
* A cell with no run is *missing* (``—``, ``--`` in LaTeX), never zero. A cell whose runs exist but
  lack the metric (a point estimate has no log likelihood) is ``n/a``.
* ``mean_of`` columns (Table 3's SYMSOL II average) are the mean of those columns' cells, and
  missing as soon as one of them is.
* Under each row with runs and published numbers: the paper's value and the difference, ours minus
  the paper's.
* Calibration (``calibration_ece`` of density methods; the paper reports none) gets its own small
  table: one column per distinct set of runs of the layout's columns.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from image2sphere.reporting.runs import Run

__all__ = [
    "Cell",
    "FilledTable",
    "build_table",
    "draw_figure",
    "format_cell",
    "latex_escape",
    "load_layouts",
    "md_escape",
    "run_status_lines",
    "table_lines",
    "to_latex",
    "to_markdown",
]

LAYOUT_FILE = Path(__file__).with_name("paper_tables.yaml")
MISSING_MD = "—"
MISSING_TEX = "--"


def load_layouts(path: str | Path = LAYOUT_FILE) -> dict[str, dict[str, Any]]:
    """Every table's layout by name (``table1`` ...), checked: ``ValueError`` naming the table and
    the entry that is wrong."""
    with open(path, encoding="utf-8") as f:
        layouts = yaml.safe_load(f)
    for name, layout in layouts.items():
        ids = [c.get("id") for c in layout.get("columns", [])]
        if not ids or len(set(ids)) != len(ids):
            raise ValueError(f"{path}: {name}: columns need unique ids, got {ids}")
        for c in layout["columns"]:
            if ("metric" in c) == ("mean_of" in c):
                raise ValueError(f"{path}: {name}: column {c['id']!r} needs exactly one of metric and mean_of")
            if c.get("better") not in ("higher", "lower"):
                raise ValueError(f"{path}: {name}: column {c['id']!r}: better must be higher or lower")
            if any(i not in ids for i in c.get("mean_of", [])):
                raise ValueError(f"{path}: {name}: column {c['id']!r}: mean_of names an unknown column")
        for r in layout.get("rows", []):
            unknown = set(r.get("published", {})) | set(r.get("published_std", {}))
            unknown -= set(ids)
            if unknown:
                raise ValueError(
                    f"{path}: {name}: row {r.get('label')!r}: published values for unknown columns {sorted(unknown)}"
                )
    return layouts


@dataclass(eq=False)
class Cell:
    """Our value of one (row, column): ``runs`` matched; ``values`` of those that have the metric."""

    runs: list[Run] = field(default_factory=list)
    values: list[float] = field(default_factory=list)
    published: float | None = None
    published_std: float | None = None
    # shown instead of the value when set (e.g. "not recorded")
    text: str | None = None

    @property
    def missing(self) -> bool:
        return not self.runs

    @property
    def not_available(self) -> bool:
        return bool(self.runs) and not self.values

    @property
    def mean(self) -> float | None:
        return sum(self.values) / len(self.values) if self.values else None

    @property
    def std(self) -> float | None:
        n = len(self.values)
        if n < 2:
            return None
        m = self.mean
        return math.sqrt(sum((v - m) ** 2 for v in self.values) / (n - 1))

    @property
    def difference(self) -> float | None:
        if self.mean is None or self.published is None:
            return None
        return self.mean - self.published


@dataclass
class FilledTable:
    name: str
    layout: dict[str, Any]
    cells: list[list[Cell]]  # [row][column]
    calibration_columns: list[str]
    calibration: list[list[Cell]]  # [row][calibration column]
    used: list[Run]
    unmatched: list[Run]
    notes: list[str]


def _with_dataset(match: dict[str, Any] | None, dataset: str | None) -> dict[str, Any]:
    match = dict(match or {})
    if dataset is not None and "dataset" in match:
        match["dataset"] = dataset
    return match


def build_table(name: str, layout: dict[str, Any], runs: list[Run], dataset: str | None = None) -> FilledTable:
    """Fill the layout of table ``name`` from ``runs``; ``dataset`` replaces the dataset every cell is
    matched on (e.g. to tabulate a small run on the built-in data)."""
    layout = copy.deepcopy(layout)
    table_match = _with_dataset(layout.get("match"), dataset)
    if (
        dataset is not None
        and "dataset" not in table_match
        and not any("dataset" in (c.get("match") or {}) for c in layout["columns"])
    ):
        table_match["dataset"] = dataset
    columns = layout["columns"]
    col_match = [_with_dataset(c.get("match"), dataset) for c in columns]
    ids = [c["id"] for c in columns]
    cells: list[list[Cell]] = []
    used: dict[Path, Run] = {}
    notes: list[str] = []
    for row in layout["rows"]:
        row_match = {**table_match, **(row.get("match") or {})}
        row_cells = []
        for c, cm in zip(columns, col_match, strict=True):
            cell = Cell(
                published=row.get("published", {}).get(c["id"]), published_std=row.get("published_std", {}).get(c["id"])
            )
            if "metric" in c:
                cell.runs = [r for r in runs if r.matches({**row_match, **cm})]
                cell.values = [r.metrics[c["metric"]] for r in cell.runs if c["metric"] in r.metrics]
                used.update({r.path: r for r in cell.runs})
                seeds = [r.seed for r in cell.runs]
                repeated = sorted({str(s) for s in seeds if seeds.count(s) > 1})
                if repeated:
                    notes.append(
                        f"{row['label']} / {c['title']}: {len(cell.runs)} runs share seed(s) {', '.join(repeated)}; "
                        "all are averaged"
                    )
            row_cells.append(cell)
        for j, c in enumerate(columns):  # derived columns, from the cells of this row
            if "mean_of" in c:
                parts = [row_cells[ids.index(i)] for i in c["mean_of"]]
                cell = row_cells[j]
                cell.runs = [r for p in parts for r in p.runs] if all(p.runs for p in parts) else []
                if cell.runs and all(p.values for p in parts):
                    cell.values = [sum(p.mean for p in parts) / len(parts)]
        cells.append(row_cells)

    # calibration: one column per distinct set of runs (the columns' match), density methods only
    cal_keys: list[tuple[str, dict[str, Any]]] = []
    for c, cm in zip(columns, col_match, strict=True):
        if "metric" in c and all(cm != m for _, m in cal_keys):
            cal_keys.append((c.get("group") or ("ECE" if not cm else c["title"]), cm))
    calibration = []
    for row in layout["rows"]:
        row_match = {**table_match, **(row.get("match") or {})}
        row_cells = []
        for _, cm in cal_keys:
            matched = [r for r in runs if r.matches({**row_match, **cm})]
            cell = Cell(
                runs=matched, values=[r.metrics["calibration_ece"] for r in matched if "calibration_ece" in r.metrics]
            )
            if cell.not_available and any("log_likelihood" in r.metrics for r in matched):
                cell.text = "not recorded"  # a density whose runs predate the calibration metrics
            row_cells.append(cell)
        calibration.append(row_cells)

    used_runs = list(used.values())
    unmatched = [r for r in runs if r.path not in used]
    smoke = [r for r in used_runs if r.smoke_test]
    if smoke:
        notes.append(
            f"{len(smoke)} of the runs are trainer.fast_dev_run smoke tests: their metrics come from one batch"
        )
    paper_dataset = (layout.get("match") or {}).get("dataset")
    if dataset is not None and paper_dataset is not None and dataset != paper_dataset:
        notes.append(
            f"runs on dataset={dataset}, the paper's table is on {paper_dataset}: "
            "the published numbers are not comparable"
        )
    # rows whose published numbers come from another paper than I2S's say where (or that they were not found)
    notes += [f"{row['label']}: {' '.join(str(row['source']).split())}" for row in layout["rows"] if row.get("source")]
    return FilledTable(
        name=name,
        layout=layout,
        cells=cells,
        calibration_columns=[k for k, _ in cal_keys],
        calibration=calibration,
        used=used_runs,
        unmatched=unmatched,
        notes=notes,
    )


# ---------------------------------------------------------------------------------------- text
def _number(x: float, digits: int, signed: bool = False) -> str:
    return f"{x:+.{digits}f}" if signed else f"{x:.{digits}f}"


def format_cell(cell: Cell, digits: int, missing: str, pm: str) -> str:
    """A cell of ours as text: its fixed text, ``missing``, ``n/a``, or the mean (``digits`` decimals) with
    ``pm`` and the standard deviation where there are several runs."""
    if cell.text is not None:
        return cell.text
    if cell.missing:
        return missing
    if cell.not_available:
        return "n/a"
    text = _number(cell.mean, digits)
    if cell.std is not None:
        text += f" {pm} {_number(cell.std, digits)}"
    return text


def _paper(cell: Cell, digits: int, missing: str, pm: str) -> str:
    if cell.published is None:
        return missing
    text = _number(cell.published, digits)
    if cell.published_std is not None:
        text += f" {pm} {_number(cell.published_std, digits)}"
    return text


def table_lines(table: FilledTable, missing: str, pm: str) -> list[tuple[str, str, list[str]]]:
    """``(row label, source, cells)`` lines: ours, then the paper's and the difference."""
    out = []
    columns = table.layout["columns"]
    for row, cells in zip(table.layout["rows"], table.cells, strict=True):
        n = max((len(c.runs) for c, col in zip(cells, columns, strict=True) if "mean_of" not in col), default=0)
        unfinished = len({r.path for c in cells for r in c.runs if r.incomplete})
        source = f"ours ({n} run{'s' if n != 1 else ''})" if n else "ours"
        if unfinished:
            source = source[:-1] + f", {unfinished} unfinished)"
        out.append(
            (
                row["label"],
                source,
                [format_cell(c, col["digits"], missing, pm) for c, col in zip(cells, columns, strict=True)],
            )
        )
        if any(c.published is not None for c in cells):
            out.append(
                ("", "paper", [_paper(c, col["digits"], missing, pm) for c, col in zip(cells, columns, strict=True)])
            )
            if any(c.difference is not None for c in cells):
                out.append(("", "difference", [
                    missing if c.difference is None else _number(c.difference, col["digits"], signed=True)
                    for c, col in zip(cells, columns, strict=True)
                ]))  # fmt: skip
    return out


def _column_titles(table: FilledTable) -> list[str]:
    return [f"{c['group']}: {c['title']}" if c.get("group") else c["title"] for c in table.layout["columns"]]


def md_escape(text: str) -> str:
    """``text`` safe inside a Markdown table cell."""
    return text.replace("|", "\\|")


def run_status_lines(used: list[Run], left_out: list[Run], unfinished: list) -> list[str]:
    """The list under a table of the runs it does not simply count: those with metrics left out of the means
    (``left_out``, not finished as configured), those counted although unfinished (``used`` runs with a
    reason), and the run directories without metrics (``unfinished``)."""
    lines = [f"- not counted: `{r.path}` ({r.incomplete})" for r in left_out]
    if left_out:
        lines.append("- (runs not counted are left out of the means; `--include-unfinished` counts them, marked)")
    lines += [f"- counted although unfinished: `{r.path}` ({r.incomplete})" for r in used if r.incomplete]
    lines += [f"- not finished: `{u.path}`: {u.reason}" for u in unfinished]
    return lines


def to_markdown(table: FilledTable, unfinished: list | None = None, left_out: list[Run] | None = None) -> str:
    """The table in Markdown: the paper's rows and columns, three lines per row (ours, the paper's,
    the difference), then calibration, the notes, the runs not counted or counted although unfinished
    (:func:`run_status_lines`), the runs without metrics and the unmatched runs."""
    layout = table.layout
    titles = _column_titles(table)
    arrows = ["↑" if c["better"] == "higher" else "↓" for c in layout["columns"]]
    lines = [f"### {layout['title']}", "", " ".join(layout.get("caption", "").split()), ""]
    lines.append("| method | | " + " | ".join(f"{t} {a}" for t, a in zip(titles, arrows, strict=True)) + " |")
    lines.append("|---|---|" + "---:|" * len(titles))
    for label, source, cells in table_lines(table, MISSING_MD, "±"):
        lines.append(f"| {md_escape(label)} | {source} | " + " | ".join(cells) + " |")
    if any(c.runs for row in table.calibration for c in row):
        lines += ["", "Calibration (expected calibration error of the highest-density regions at 10%..90% mass,"
                  " lower is better; point estimates n/a; the paper reports none):", ""]  # fmt: skip
        lines.append("| method | " + " | ".join(table.calibration_columns) + " |")
        lines.append("|---|" + "---:|" * len(table.calibration_columns))
        for row, cells in zip(layout["rows"], table.calibration, strict=True):
            lines.append(
                f"| {md_escape(row['label'])} | " + " | ".join(format_cell(c, 3, MISSING_MD, "±") for c in cells) + " |"
            )
    lines += ["", f"{MISSING_MD}: no finished run; n/a: the method has no such metric (not recorded: its runs "
              "have no calibration metrics, written before they existed); ± the sample standard deviation over "
              "runs (seeds); difference: ours minus the paper's."]  # fmt: skip
    lines += [f"- note: {n}" for n in table.notes]
    lines += run_status_lines(table.used, left_out or [], unfinished or [])
    for r in table.unmatched:
        lines.append(
            f"- not in this table: `{r.path}` (model={r.get('model', None)}, dataset={r.get('dataset', None)})"
        )
    return "\n".join(lines) + "\n"


_TEX_ESCAPES = {
    "\\": r"\textbackslash{}",
    "&": r"\&",
    "%": r"\%",
    "$": r"\$",
    "#": r"\#",
    "_": r"\_",
    "{": r"\{",
    "}": r"\}",
    "~": r"\textasciitilde{}",
    "^": r"\textasciicircum{}",
}


def latex_escape(text: str) -> str:
    """``text`` with LaTeX's special characters escaped (safe inside a tabular cell)."""
    return "".join(_TEX_ESCAPES.get(ch, ch) for ch in str(text))


def to_latex(table: FilledTable) -> str:
    """The table as a LaTeX ``table`` (booktabs): the column groups as a header row, three lines per
    row (ours, the paper's, the difference)."""
    layout = table.layout
    columns = layout["columns"]
    ncol = len(columns)
    out = [
        r"\begin{table}[t]",
        r"\centering",
        r"\caption{" + latex_escape(" ".join(layout.get("caption", layout["title"]).split())) + "}",
        r"\label{tab:" + latex_escape(table.name) + "}",
        r"\begin{tabular}{ll" + "c" * ncol + "}",
        r"\toprule",
    ]
    groups = [c.get("group") for c in columns]
    if any(groups):
        header, rules, j = ["", ""], [], 0
        while j < ncol:
            k = j
            while k + 1 < ncol and groups[k + 1] == groups[j]:
                k += 1
            span = k - j + 1
            header.append(r"\multicolumn{" + str(span) + "}{c}{" + latex_escape(groups[j] or "") + "}")
            if groups[j]:
                rules.append(r"\cmidrule(lr){" + f"{j + 3}-{k + 3}" + "}")
            j = k + 1
        out.append(" & ".join(header) + r" \\")
        out.append(" ".join(rules))
    arrows = [r"$\uparrow$" if c["better"] == "higher" else r"$\downarrow$" for c in columns]
    out.append(
        " & ".join(["", ""] + [latex_escape(c["title"]) + a for c, a in zip(columns, arrows, strict=True)]) + r" \\"
    )
    out.append(r"\midrule")
    for label, source, cells in table_lines(table, MISSING_TEX, r"$\pm$"):
        if label and out[-1] != r"\midrule":
            out.append(r"\midrule")
        body = [c.replace("±", r"$\pm$") for c in cells]
        out.append(" & ".join([latex_escape(label), latex_escape(source)] + body) + r" \\")
    out += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
    return "\n".join(out) + "\n"


# ---------------------------------------------------------------------------------------- figure
def draw_figure(table: FilledTable, path: str | Path) -> Path | None:
    """The layout's figure (``line``: each column against a config key, ours with error bars and the
    paper's dashed; ``bars``: per column, a bar per row with runs and the paper's value as a tick) as
    a PNG at ``path``; ``None`` when the layout has no figure or no cell has a value."""
    spec = table.layout.get("figure")
    if not spec or not any(c.values for row in table.cells for c in row):
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    columns = table.layout["columns"]
    rows = table.layout["rows"]
    path = Path(path)
    if spec["kind"] == "line":
        key = spec["x"]
        xs = [float(next(iter(v for k, v in r["match"].items() if k == key))) for r in rows]
        fig, axes = plt.subplots(1, len(columns), figsize=(4 * len(columns), 3.2), squeeze=False)
        for j, (c, ax) in enumerate(zip(columns, axes[0], strict=True)):
            ours = [(x, row[j]) for x, row in zip(xs, table.cells, strict=True) if row[j].values]
            if ours:
                ax.errorbar([x for x, _ in ours], [cell.mean for _, cell in ours],
                            yerr=[cell.std or 0.0 for _, cell in ours], marker="o", capsize=3,
                            label="ours")  # fmt: skip
            paper = [
                (x, row[j].published) for x, row in zip(xs, table.cells, strict=True) if row[j].published is not None
            ]
            if paper:
                ax.plot([x for x, _ in paper], [p for _, p in paper], "k--", marker="s", label="paper")
            ax.set_xlabel(key)
            ax.set_title(f"{c['title']} ({c['better']} is better)")
            ax.set_xticks(xs)
            ax.legend()
    else:
        with_runs = [i for i, row in enumerate(table.cells) if any(c.values for c in row)]
        width = 0.8 / max(len(with_runs), 1)
        fig, ax = plt.subplots(figsize=(max(6, 0.9 * len(columns) * max(1, len(with_runs)) ** 0.5 + 2), 4))
        for k, i in enumerate(with_runs):
            xs = [j + (k - (len(with_runs) - 1) / 2) * width for j in range(len(columns))]
            cells = table.cells[i]
            # a cell without a value is no bar (NaN), never a bar of height 0
            ax.bar(xs, [c.mean if c.values else math.nan for c in cells], width,
                   yerr=[c.std or 0.0 for c in cells], label=rows[i]["label"], capsize=2)  # fmt: skip
            pub = [(x, c.published) for x, c in zip(xs, cells, strict=True) if c.published is not None]
            ax.scatter([x for x, _ in pub], [p for _, p in pub], marker="_", color="k", s=120, zorder=3,
                       label="paper" if k == 0 else None)  # fmt: skip
        ax.set_xticks(range(len(columns)))
        ax.set_xticklabels([t for t in _column_titles(table)], rotation=45, ha="right")
        ax.legend(fontsize=7)
    fig.suptitle(table.layout["title"])
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
