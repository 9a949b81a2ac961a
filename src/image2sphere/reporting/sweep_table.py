"""A table of any sweep: one row per setting, the overrides that differ between the runs as columns,
and the headline test metrics as the mean +- sample standard deviation over seeds.

``python -m src.tables DIR`` writes this table for runs that were not launched for one of the paper's
tables (those are :mod:`.tables`): a multirun of one's own (``python -m src.train -m lmax=2,4
seed=0,1``), an Optuna study (``hparams_search=optuna_i2s``), a small sweep of ``conf/table/small/``,
or several such directories pooled.

Rules
-----
* A run's setting is its command-line overrides (``.hydra/overrides.yaml``) without ``seed``: the
  seeds of one setting are what a row averages. A key is a column only where its value differs
  between the runs; a run that does not set it on the command line shows its composed value (the
  group's choice or ``.hydra/config.yaml``), ``—`` when its config has no such key.
* The metrics are the class means of ``metrics.json``, every metric any of the runs has, in the fixed order of
  :func:`~image2sphere.reporting.metrics_table.metric_layout`: the main table has the headline metrics
  (:data:`SWEEP_METRICS`, always), then the method's own (``log_likelihood_exact``, any key not known there);
  a key ``<metric>_calibrated`` (the metric after recalibration) adds a column right after that metric's.
  Under it, where the runs have them (:func:`further_sections`): a table of the run's numbers and timings (test
  loss, temperature, test images, ``*_seconds``), one of the HDR coverage, one of the HDR coverage after
  recalibration. A row none of whose runs has a metric shows ``n/a``, never 0. The spread is the sample
  standard deviation (``n - 1``), shown for two runs or more, as in the paper's tables.
* The runs are those the caller counts (:func:`~image2sphere.reporting.runs.counted_runs`); runs counted
  although unfinished (``--include-unfinished``) are marked in the ``runs`` column, ``N (k unfinished)``.
* The runs of an Optuna study (``hydra.sweeper.direction`` in their ``.hydra/hydra.yaml``) are ordered
  by the study's objective (``optimized_metric``), best first, and its column is marked; any other
  sweep keeps the order of its jobs.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from image2sphere.config_text import override_key
from image2sphere.reporting.metrics_table import CALIBRATED, TABLE_COLUMNS, metric_layout
from image2sphere.reporting.runs import Run
from image2sphere.reporting.tables import (
    MISSING_MD,
    MISSING_TEX,
    Cell,
    format_cell,
    latex_escape,
    md_escape,
    run_status_lines,
)

__all__ = [
    "SWEEP_METRICS",
    "SWEEP_NAME",
    "Objective",
    "SweepRow",
    "SweepTable",
    "build_sweep_table",
    "further_sections",
    "is_sweep",
    "metric_columns",
    "study_objective",
    "sweep_header",
    "sweep_lines",
    "sweep_to_latex",
    "sweep_to_markdown",
    "varying_keys",
]

# the file name of the written table (<out>/sweep.md, <out>/sweep.tex) and its name in wandb
SWEEP_NAME = "sweep"
# The metrics of the table, in order: (key of metrics.json, column title, number format). The same list
# as the test-metrics table that src.train and src.eval print, so that a metric added there (one line)
# is a column here as well.
SWEEP_METRICS: tuple[tuple[str, str, str], ...] = TABLE_COLUMNS
# the titles of the tables under the main one
FURTHER_TITLE = "Further numbers (test loss, temperature, test images; wall times in seconds)"
COVERAGE_TITLE = ("HDR coverage (class means: the fraction of the (image, rotation) pairs inside the "
                  "highest-density region of each mass)")  # fmt: skip
# overrides that are not part of a setting: the seeds are what a row averages over
NOT_A_SETTING = ("seed",)

_ABSENT = object()


def is_sweep(runs: list[Run]) -> bool:
    """Whether ``runs`` are a sweep to tabulate: jobs of a Hydra multirun, or several runs."""
    return len(runs) > 1 or any(r.multirun_job for r in runs)


# ---------------------------------------------------------------------------------------- settings
def _overrides(run: Run) -> dict[str, str]:
    """``key -> value`` (as typed) of the run's command-line overrides; the last of a key wins."""
    out = {}
    for text in run.overrides:
        key, (_, eq, value) = override_key(text), text.partition("=")
        if eq and key and not key.startswith(("hydra.", "hydra/")):
            out[key] = value
    return out


def _value(run: Run, key: str) -> Any:
    """The value of ``key`` as the run's command line typed it, else as its config composed it (``_ABSENT``)."""
    overrides = _overrides(run)
    return overrides[key] if key in overrides else run.get(key, _ABSENT)


def _canonical(value: Any) -> Any:
    """What two values are compared by: ``"4"`` (typed) equals ``4`` (composed), ``null`` equals None."""
    if value is _ABSENT:
        return ("absent",)
    if isinstance(value, (dict, list)):
        return json.dumps(value, sort_keys=True)
    text = str(value).strip()
    if value is None or text in ("null", "~", "None"):
        return None
    if isinstance(value, bool) or text.lower() in ("true", "false"):
        return text.lower()
    try:
        number = float(text)
    except ValueError:
        return text
    return text if math.isnan(number) else number


def _display(value: Any) -> str | None:
    """A value as the table shows it (None: absent); a long float of a sampler is cut to 6 digits."""
    if value is _ABSENT:
        return None
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (dict, list)):
        return json.dumps(value, separators=(",", ":"))
    text = str(value)
    if len(text) > 8 and re.fullmatch(r"[-+]?\d*\.\d+(e[-+]?\d+)?|[-+]?\d+e[-+]?\d+", text, re.IGNORECASE):
        return f"{float(text):.6g}"
    return text


def _natural(path: Path) -> list:
    """Sort key of a path with its numbers as numbers (job 10 after job 9)."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(path))]


def varying_keys(runs: list[Run]) -> list[str]:
    """The override keys (not ``seed``) whose value differs between ``runs``, in the order they first appear."""
    keys: list[str] = []
    for run in runs:
        keys += [k for k in _overrides(run) if k not in keys and k not in NOT_A_SETTING]
    return [k for k in keys if len({repr(_canonical(_value(r, k))) for r in runs}) > 1]


# ---------------------------------------------------------------------------------------- metrics
def metric_columns(runs: list[Run], objective: str | None = None) -> list[tuple[str, str, str]]:
    """The main table's metrics: :data:`SWEEP_METRICS`, then the method's own that any run has (the layout of
    :func:`~image2sphere.reporting.metrics_table.metric_layout`), each followed by its ``_calibrated`` twin where
    a run has one (titled as in the per-run table, e.g. ``LL recal.``); the objective first where it is none of
    them."""
    layout = metric_layout(k for r in runs for k in r.metrics)
    main = [c for c in layout.main if c[0] not in {m for m, _, _ in SWEEP_METRICS}]
    twins = {m: (m, title, fmt) for m, title, fmt in main if m.endswith(CALIBRATED)}
    columns = []
    for metric, title, fmt in [*SWEEP_METRICS, *(c for c in main if c[0] not in twins)]:
        columns.append((metric, title, fmt))
        twin = twins.pop(metric + CALIBRATED, None)
        if twin is not None:
            columns.append(twin)
    columns += list(twins.values())  # a recalibrated metric whose own value no run has
    if objective is not None and objective not in {m for m, _, _ in columns}:
        columns.insert(0, (objective, objective, "{:.3f}"))
    return columns


def further_sections(runs: list[Run], shown: set[str] = frozenset()) -> list[tuple[str, list[tuple[str, str, str]]]]:
    """The tables under the main one, ``(title, columns)``: the run's numbers and timings, the HDR coverage,
    and the HDR coverage after recalibration; each only where a run has one of its metrics, none of ``shown``."""
    layout = metric_layout(k for r in runs for k in r.metrics)
    numbers = [*layout.numbers, *((k, f"{title} (s)", fmt) for k, title, fmt in layout.timings)]
    sections = [
        (FURTHER_TITLE, numbers),
        (COVERAGE_TITLE, layout.coverage),
        ("HDR coverage after recalibration (class means)", layout.coverage_calibrated),
    ]
    out = []
    for title, columns in sections:
        columns = [c for c in columns if c[0] not in shown]
        if columns:
            out.append((title, columns))
    return out


def _digits(fmt: str) -> int:
    match = re.search(r"\.(\d+)[fe%]", fmt)
    return int(match.group(1)) if match else 3


# ---------------------------------------------------------------------------------------- the study
@dataclass(frozen=True)
class Objective:
    """An Optuna study's objective: the metric (``optimized_metric``) and ``maximize`` or ``minimize``."""

    metric: str
    direction: str
    study: str | None = None


def _direction(value: Any) -> str | None:
    if isinstance(value, list):  # one objective given as a list
        value = value[0] if len(value) == 1 else None
    text = str(value).lower() if value is not None else ""
    return "maximize" if "max" in text else "minimize" if "min" in text else None


def study_objective(runs: list[Run]) -> tuple[Objective | None, list[str]]:
    """The objective that every run's sweeper optimised (None where a run has none or they differ), and notes."""
    if not runs:
        return None, []
    found = set()
    for run in runs:
        sweeper = run.hydra.get("sweeper") or {}
        direction, metric = _direction(sweeper.get("direction")), run.get("optimized_metric", None)
        if direction is None or not isinstance(metric, str):
            return None, []
        found.add(Objective(metric, direction, sweeper.get("study_name")))
    if len(found) != 1:
        shown = ", ".join(sorted(f"{o.metric} ({o.direction})" for o in found))
        return None, [f"the runs come from studies of different objectives ({shown}): rows in the order of the jobs"]
    notes = []
    for parent in sorted({r.path.parent for r in runs}, key=_natural):
        results = parent / "optimization_results.yaml"
        try:
            best = (yaml.safe_load(results.read_text(encoding="utf-8")) or {}).get("best_value")
        except (OSError, yaml.YAMLError, AttributeError):
            continue
        if best is not None:
            notes.append(f"the study's best value in `{results}`: {best}")
    return found.pop(), notes


# ---------------------------------------------------------------------------------------- the table
@dataclass
class SweepRow:
    """One setting: the value of each key (None: absent from the run's config), its runs and metric cells
    (``sections``: the cells of each table under the main one)."""

    setting: list[str | None]
    runs: list[Run]
    cells: list[Cell]
    sections: list[list[Cell]] = field(default_factory=list)

    @property
    def unfinished(self) -> int:
        """How many of the row's runs are counted although not finished (``--include-unfinished``)."""
        return sum(1 for r in self.runs if r.incomplete)


@dataclass
class SweepTable:
    keys: list[str]
    columns: list[tuple[str, str, str]]  # (metric, title, format)
    rows: list[SweepRow]
    objective: Objective | None = None
    notes: list[str] = field(default_factory=list)
    sources: list[str] = field(default_factory=list)
    # the tables under the main one: (title, columns) of :func:`further_sections`
    sections: list[tuple[str, list[tuple[str, str, str]]]] = field(default_factory=list)

    @property
    def used(self) -> list[Run]:
        return [r for row in self.rows for r in row.runs]


def build_sweep_table(runs: list[Run], sources: list[str] | None = None) -> SweepTable:
    """One row per setting of ``runs`` (see the module's rules); ``sources`` name the directories read."""
    runs = sorted(runs, key=lambda r: _natural(r.path))
    objective, notes = study_objective(runs)
    keys = varying_keys(runs)
    columns = metric_columns(runs, objective.metric if objective else None)
    sections = further_sections(runs, {m for m, _, _ in columns})
    groups: dict[tuple, list[Run]] = {}
    for run in runs:
        groups.setdefault(tuple(repr(_canonical(_value(run, k))) for k in keys), []).append(run)
    rows = []

    def cells_of(members: list[Run], metrics: list[tuple[str, str, str]]) -> list[Cell]:
        return [Cell(runs=members, values=[r.metrics[m] for r in members if m in r.metrics]) for m, _, _ in metrics]

    for members in groups.values():
        setting = [_display(_value(members[0], k)) for k in keys]
        extra = [cells_of(members, section) for _, section in sections]
        rows.append(SweepRow(setting, members, cells_of(members, columns), extra))
        seeds = [str(r.seed) for r in members]
        repeated = sorted({s for s in seeds if seeds.count(s) > 1})
        if repeated:
            label = ", ".join(f"{k}={v}" for k, v in zip(keys, rows[-1].setting, strict=True)) or "all runs"
            notes.append(f"{label}: {len(members)} runs share seed(s) {', '.join(repeated)}; all are averaged")
    if objective is not None:
        j = [m for m, _, _ in columns].index(objective.metric)
        sign = -1.0 if objective.direction == "maximize" else 1.0
        rows.sort(key=lambda row: (row.cells[j].mean is None, sign * (row.cells[j].mean or 0.0)))
    smoke = [r for r in runs if r.smoke_test]
    if smoke:
        notes.append(f"{len(smoke)} of the runs are trainer.fast_dev_run smoke tests: their metrics are of one batch")
    return SweepTable(keys, columns, rows, objective, notes, [str(s) for s in sources or []], sections)


# ---------------------------------------------------------------------------------------- text
def _titles(columns: list[tuple[str, str, str]], objective: Objective | None, up: str, down: str,
            escape=lambda s: s) -> list[str]:  # fmt: skip
    titles = []
    for metric, title, _ in columns:
        if objective is not None and metric == objective.metric:
            arrow = up if objective.direction == "maximize" else down
            titles.append(f"{escape(title)} (objective {arrow})")
        else:
            titles.append(escape(title))
    return titles


def _runs_cell(row: SweepRow) -> str:
    return f"{len(row.runs)} ({row.unfinished} unfinished)" if row.unfinished else str(len(row.runs))


def _metric_cells(cells: list[Cell], columns: list[tuple[str, str, str]], missing: str, pm: str) -> list[str]:
    return [format_cell(c, _digits(fmt), missing, pm) for c, (_, _, fmt) in zip(cells, columns, strict=True)]


def sweep_lines(table: SweepTable, missing: str, pm: str, section: int | None = None) -> list[list[str]]:
    """Each row's cells: the setting's values, the metrics (mean ``pm`` std, ``n/a``) and the number of runs
    (``N (k unfinished)`` where unfinished runs are counted); of the main table, or of ``table.sections[section]``
    (no number of runs)."""
    out = []
    for row in table.rows:
        setting = [missing if v is None else v for v in row.setting] if table.keys else ["all runs"]
        if section is None:
            out.append([*setting, *_metric_cells(row.cells, table.columns, missing, pm), _runs_cell(row)])
        else:
            out.append([*setting, *_metric_cells(row.sections[section], table.sections[section][1], missing, pm)])
    return out


def sweep_header(table: SweepTable, up: str = "↑", down: str = "↓", escape=lambda s: s,
                 section: int | None = None) -> list[str]:  # fmt: skip
    """The column titles of :func:`sweep_lines`: the keys (or ``setting``), the metrics, ``runs``."""
    keys = [escape(k) for k in table.keys or ["setting"]]
    if section is not None:
        return [*keys, *_titles(table.sections[section][1], None, up, down, escape)]
    return [*keys, *_titles(table.columns, table.objective, up, down, escape), "runs"]


def _heading(table: SweepTable) -> str:
    n, settings = len(table.used), len(table.rows)
    unfinished = sum(row.unfinished for row in table.rows)
    finished = n - unfinished
    counts = f"{finished} finished run{'s' if finished != 1 else ''}"
    if unfinished:
        counts += f" and {unfinished} unfinished"
    counts += f", {settings} setting{'s' if settings != 1 else ''}"
    if table.objective is not None:
        study = f" {table.objective.study}" if table.objective.study else ""
        return f"Optuna study{study}: {counts}"
    return f"Sweep: {counts}"


def _explanation(table: SweepTable) -> str:
    text = ("One row per setting: the overrides that differ between the runs (the seed is what a row averages "
            "over); the class means of each run's metrics.json, mean ± sample standard deviation over the row's "
            "runs.")  # fmt: skip
    if table.objective is not None:
        o = table.objective
        text += f" Ordered by the study's objective {o.metric} ({o.direction}), best first."
    return text


def _markdown_table(header: list[str], lines: list[list[str]], keys: int) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * keys + "---:|" * (len(header) - keys)]
    return out + ["| " + " | ".join(md_escape(c) for c in cells) + " |" for cells in lines]


def sweep_to_markdown(table: SweepTable, unfinished: list | None = None, left_out: list[Run] | None = None) -> str:
    """The table in Markdown, the tables of its further metrics, then its legend, the notes, the runs left
    out of the means (``left_out``: not finished as configured), those counted although unfinished, and the
    runs without metrics (``unfinished``)."""
    lines = [f"### {_heading(table)}", ""]
    if table.sources:
        lines += [", ".join(f"`{s}`" for s in table.sources), ""]
    lines += [_explanation(table), ""]
    keys = max(len(table.keys), 1)
    lines += _markdown_table(sweep_header(table, escape=md_escape), sweep_lines(table, MISSING_MD, "±"), keys)
    for i, (title, _) in enumerate(table.sections):
        header = sweep_header(table, escape=md_escape, section=i)
        lines += ["", f"{title}:", "", *_markdown_table(header, sweep_lines(table, MISSING_MD, "±", i), keys)]
    legend = (f"{MISSING_MD}: the run's config has no such key; n/a: no run of the row has the metric; ± the sample "
              "standard deviation over the row's runs (seeds), none for a single run.")  # fmt: skip
    recalibrated = [title for m, title, _ in table.columns if m.endswith(CALIBRATED)]
    if recalibrated:
        legend += f" {', '.join(recalibrated)}: after recalibration (`<metric>{CALIBRATED}` of metrics.json)."
    lines += ["", legend]
    lines += [f"- note: {n}" for n in table.notes]
    lines += run_status_lines(table.used, left_out or [], unfinished or [])
    return "\n".join(lines) + "\n"


def _latex_table(caption: str, label: str, header: list[str], lines: list[list[str]], keys: int) -> list[str]:
    out = [
        r"\begin{table}[t]",
        r"\centering",
        r"\caption{" + caption + "}",
        r"\label{tab:" + label + "}",
        r"\begin{tabular}{" + "l" * keys + "r" * (len(header) - keys) + "}",
        r"\toprule",
        " & ".join(header) + r" \\",
        r"\midrule",
    ]
    for cells in lines:
        out.append(" & ".join(latex_escape(c).replace("±", r"$\pm$") for c in cells) + r" \\")
    return out + [r"\bottomrule", r"\end{tabular}", r"\end{table}"]


def sweep_to_latex(table: SweepTable) -> str:
    """The table as a LaTeX ``table`` (booktabs), every value escaped; each table of further metrics after it."""
    keys = max(len(table.keys), 1)
    caption = latex_escape(_heading(table)) + ". " + latex_escape(_explanation(table)).replace("±", r"$\pm$")
    header = sweep_header(table, r"$\uparrow$", r"$\downarrow$", escape=latex_escape)
    out = _latex_table(caption, SWEEP_NAME, header, sweep_lines(table, MISSING_TEX, "±"), keys)
    for i, (title, _) in enumerate(table.sections):
        header = sweep_header(table, escape=latex_escape, section=i)
        lines = sweep_lines(table, MISSING_TEX, "±", i)
        out += ["", *_latex_table(latex_escape(title), f"{SWEEP_NAME}-{i + 1}", header, lines, keys)]
    return "\n".join(out) + "\n"
