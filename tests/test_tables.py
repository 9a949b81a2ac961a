"""``python -m src.tables`` on hand-written run directories: means and spreads over seeds, per-class
layouts, missing cells, the published numbers where the paper has them, LaTeX escaping, unfinished
runs, and never overwriting a table already written."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from src.tables import main as tables_main

from image2sphere.reporting import build_table, draw_figure, find_runs, load_layouts, to_latex, to_markdown
from image2sphere.reporting.tables import latex_escape

REPO = Path(__file__).resolve().parents[1]
LAYOUTS = load_layouts()
MODELNET = ["bathtub", "bed", "chair", "desk", "dresser", "monitor", "night_stand", "sofa", "table", "toilet"]


def make_run(
    root: Path,
    name: str,
    choices: dict,
    config: dict | None = None,
    metrics: dict | None = None,
    overrides: list[str] | None = None,
) -> Path:
    """A run directory as Hydra and src.train leave it; ``metrics=None``: not finished."""
    run = root / name
    (run / ".hydra").mkdir(parents=True)
    config = {"seed": 0, "lmax": 6, "task_name": "t", "trainer": {"fast_dev_run": False}, **(config or {})}
    (run / ".hydra" / "config.yaml").write_text(yaml.safe_dump(config))
    hydra = {"hydra": {"runtime": {"choices": {"hydra/sweeper": "table", **choices}}}}
    (run / ".hydra" / "hydra.yaml").write_text(yaml.safe_dump(hydra))
    (run / ".hydra" / "overrides.yaml").write_text(
        yaml.safe_dump(overrides or [f"{k}={v}" for k, v in choices.items()])
    )
    if metrics is not None:
        (run / "metrics.json").write_text(json.dumps(metrics))
    return run


def accuracy_metrics(acc15: float, acc30: float, median: float, **extra) -> dict:
    return {"acc15": acc15, "acc30": acc30, "median_error_deg": median, "n_images": 100.0, **extra}


def table_lines(markdown: str) -> dict[tuple[str, str], list[str]]:
    """``(row label, source) -> cells`` of the main Markdown table (a blank label repeats the last)."""
    out, label = {}, None
    for line in markdown.splitlines():
        if not line.startswith("| ") or line.startswith("| method"):
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 3 or cells[1] not in ("paper", "difference") and not cells[1].startswith("ours"):
            continue
        label = cells[0] or label
        out[(label, cells[1].split(" (")[0])] = cells[2:]
    return out


# ------------------------------------------------------------------------------- aggregation
def test_mean_and_sample_std_over_seeds_next_to_the_paper(tmp_path):
    sweep = tmp_path / "sweep"
    values = {0: (0.50, 0.60, 40.0), 1: (0.60, 0.70, 30.0), 2: (0.70, 0.80, 20.0)}
    for seed, v in values.items():
        make_run(sweep, f"{seed}", {"table": "table7", "model": "i2s", "dataset": "modelnet10_limited"},
                 {"seed": seed, "lmax": 2}, accuracy_metrics(*v))  # fmt: skip
    runs, unfinished = find_runs([sweep])
    assert len(runs) == 3 and not unfinished
    filled = build_table("table7", LAYOUTS["table7"], runs)
    cell = filled.cells[0][0]  # L=2, Acc@15
    assert cell.mean == pytest.approx(0.6) and cell.std == pytest.approx(0.1)  # sample std (n - 1)
    assert cell.difference == pytest.approx(0.6 - 0.560)
    lines = table_lines(to_markdown(filled))
    assert lines[("L=2", "ours")] == ["0.600 ± 0.100", "0.700 ± 0.100", "30.0 ± 10.0"]
    assert lines[("L=2", "paper")] == ["0.560", "0.656", "33.6"]
    assert lines[("L=2", "difference")] == ["+0.040", "+0.044", "-3.6"]
    # L=4..10 have no run: missing cells, never zeros, and no difference line
    assert lines[("L=4", "ours")] == ["—", "—", "—"]
    assert ("L=4", "difference") not in lines
    assert "ours (3 runs)" in to_markdown(filled)


def test_a_single_run_has_no_spread_and_runs_of_other_tables_are_listed(tmp_path):
    make_run(
        tmp_path, "a", {"model": "i2s", "dataset": "modelnet10_limited"}, {"lmax": 4}, accuracy_metrics(0.5, 0.6, 40.0)
    )
    make_run(tmp_path, "b", {"model": "ipdf", "dataset": "symsol1"}, {}, accuracy_metrics(0.1, 0.2, 90.0))
    filled = build_table("table7", LAYOUTS["table7"], find_runs([tmp_path])[0])
    assert filled.cells[1][0].std is None
    text = to_markdown(filled)
    assert table_lines(text)[("L=4", "ours")] == ["0.500", "0.600", "40.0"]
    assert re.search(r"not in this table: `.*b` \(model=ipdf, dataset=symsol1\)", text)


def test_per_class_layout_of_table5_and_published_values_where_they_belong(tmp_path):
    per_class = {f"median_error_deg/{c}": 10.0 + i for i, c in enumerate(MODELNET)}
    for seed in (0, 1):
        metrics = {**accuracy_metrics(0.7, 0.7, 14.5 + seed), **per_class, "median_error_deg/bed": 3.0 + seed}
        make_run(tmp_path, f"i2s{seed}", {"model": "i2s", "dataset": "modelnet10"}, {"seed": seed}, metrics)
    filled = build_table("table5", LAYOUTS["table5"], find_runs([tmp_path])[0])
    text = to_markdown(filled)
    header = next(line for line in text.splitlines() if line.startswith("| method"))
    assert [h.strip() for h in header.strip("|").split("|")][2:] == [
        "avg. ↓", "bathtub ↓", "bed ↓", "chair ↓", "desk ↓", "dresser ↓", "monitor ↓", "n. stand ↓", "sofa ↓",
        "table ↓", "toilet ↓",
    ]  # fmt: skip
    lines = table_lines(text)
    ours = lines[("I2S", "ours")]
    assert ours[0] == "15.0 ± 0.7" and ours[2] == "3.5 ± 0.7" and ours[1] == "10.0 ± 0.0" and ours[-1] == "19.0 ± 0.0"
    # the paper's per-class numbers (its Table 5, transcribed by hand here, independently of the data file)
    assert lines[("I2S", "paper")][:3] == ["16.3 ± 2.9", "124.7 ± 28.1", "3.1 ± 0.0"]
    assert lines[("Mohlin et al. 2020", "paper")][1] == "89.1"
    assert lines[("Prokudin et al. 2018", "paper")][4] == "117.2"
    assert lines[("Mohlin et al. 2020", "ours")] == ["—"] * 11


def test_published_numbers_of_every_table_spot_checked():
    """A few numbers of each of the paper's tables, read off the paper by hand."""

    def published(table, label, column):
        row = next(r for r in LAYOUTS[table]["rows"] if r["label"] == label)
        return row["published"][column]

    assert published("table1", "Murphy et al. 2021 (IPDF)", "median") == 21.5
    assert published("table1", "Liao et al. 2019", "acc30") == 0.583
    assert published("table2", "Mahendran et al. 2018", "boat") == 20.5
    assert published("table2", "Tulsiani & Malik 2015", "tvmonitor") == 15.4
    assert published("table3", "I2S (10k)", "cylO") == 3.87
    assert published("table3", "Gilitschenski et al. 2020 (full)", "cone") == 3.84
    assert published("table3", "Murphy et al. 2021 (IPDF, 10k)", "icosa") == -18.34
    assert published("table4", "Icosahedral group version", "acc30") == 0.582
    assert published("table6", "Brégier 2021 (9D)", "acc15") == 0.129
    assert published("table7", "L=8", "median") == 43.7
    assert published("table8", "I2S, two SO(3) convolutions", "full_median") == 19.0
    assert published("table8", "I2S, no SO(3) convolution", "lim_acc15") == 0.616


def test_symsol_columns_come_from_their_own_runs_and_the_average_needs_all_three(tmp_path):
    shapes1 = {"cone": 1.0, "cyl": 2.0, "tet": 3.0, "cube": 4.0, "icosa": 5.0}
    ll = {"log_likelihood": 3.0, **{f"log_likelihood/{s}": v for s, v in shapes1.items()}}
    make_run(tmp_path, "s1", {"model": "i2s", "dataset": "symsol1"}, {"dataset": {"num_views": None}}, ll)
    for shape, value in (("sphereX", 1.0), ("cylO", 2.0), ("tetX", 6.0)):
        make_run(tmp_path, shape, {"model": "i2s", "dataset": "symsol2"},
                 {"dataset": {"num_views": None, "shape": shape}}, {"log_likelihood": value})  # fmt: skip
    # IPDF with 10k images: SYMSOL I and two of the three SYMSOL II shapes only
    make_run(tmp_path, "p1", {"model": "ipdf", "dataset": "symsol1"}, {"dataset": {"num_views": 10000}}, ll)
    for shape in ("sphereX", "cylO"):
        make_run(tmp_path, f"p{shape}", {"model": "ipdf", "dataset": "symsol2"},
                 {"dataset": {"num_views": 10000, "shape": shape}}, {"log_likelihood": 1.0})  # fmt: skip
    filled = build_table("table3", LAYOUTS["table3"], find_runs([tmp_path])[0])
    lines = table_lines(to_markdown(filled))
    assert lines[("I2S (full)", "ours")] == [
        "3.00",
        "1.00",
        "2.00",
        "3.00",
        "4.00",
        "5.00",
        "3.00",
        "1.00",
        "2.00",
        "6.00",
    ]
    assert lines[("Murphy et al. 2021 (IPDF, 10k)", "ours")][6:] == ["—", "1.00", "1.00", "—"]
    # the 10k runs are not the full-data rows
    assert lines[("Murphy et al. 2021 (IPDF, full)", "ours")] == ["—"] * 10


def test_small_symsol_layout_separates_the_one_model_of_symsol_one_from_each_shapes_own(tmp_path):
    """--table small_symsol: a run on the five shapes fills SYMSOL I (its overall and per-shape log
    likelihood), a run of one shape fills that shape's SYMSOL II column and never SYMSOL I's average;
    the rows follow dataset.label and the model, with mean +- std over seeds."""
    shapes1 = {"cone": 1.0, "cyl": 2.0, "tet": 3.0, "cube": 4.0, "icosa": 5.0}
    for seed, shift in ((0, 0.0), (1, 1.0)):
        ll = {"log_likelihood": 3.0 + shift, **{f"log_likelihood/{k}": v + shift for k, v in shapes1.items()}}
        make_run(tmp_path, f"s1_{seed}", {"model": "i2s", "dataset": "symsol_rendered"},
                 {"seed": seed, "dataset": {"shape": None, "label": "random"}}, ll)  # fmt: skip
    for shape, value in (("sphereX", 1.0), ("cylO", 2.0), ("tetX", 6.0)):
        make_run(tmp_path, shape, {"model": "i2s", "dataset": "symsol_rendered"},
                 {"dataset": {"shape": shape, "label": "random"}}, {"log_likelihood": value})  # fmt: skip
    make_run(tmp_path, "all_tetX", {"model": "i2s", "dataset": "symsol_rendered"},
             {"dataset": {"shape": "tetX", "label": "all"}}, {"log_likelihood": 7.0})  # fmt: skip
    filled = build_table("small_symsol", LAYOUTS["small_symsol"], find_runs([tmp_path])[0])
    lines = table_lines(to_markdown(filled))
    random_row = [k for k in lines if k[0].startswith("I2S, one random") and k[1].startswith("ours")][0]
    all_row = [k for k in lines if k[0].startswith("I2S, the loss averaged") and k[1].startswith("ours")][0]
    assert lines[random_row][:6] == ["3.50 ± 0.71", "1.50 ± 0.71", "2.50 ± 0.71", "3.50 ± 0.71", "4.50 ± 0.71",
                                     "5.50 ± 0.71"]  # fmt: skip
    assert lines[random_row][6:] == ["3.00", "1.00", "2.00", "6.00"]
    assert lines[all_row] == ["—"] * 9 + ["7.00"]


def test_a_point_estimate_reads_na_not_missing(tmp_path):
    make_run(tmp_path, "r", {"model": "regression_6d", "dataset": "symsol1"}, {"dataset": {"num_views": None}},
             {"acc15": 0.1, "acc30": 0.2, "median_error_deg": 50.0})  # fmt: skip
    layout = {**LAYOUTS["table3"], "rows": [{"label": "6D", "match": {"model": "regression_6d"}}]}
    filled = build_table("t", layout, find_runs([tmp_path])[0])
    assert table_lines(to_markdown(filled))[("6D", "ours")][:6] == ["n/a"] * 6


def test_calibration_table_from_the_runs_that_have_it(tmp_path):
    for seed, ece in ((0, 0.02), (1, 0.04)):
        make_run(tmp_path, f"i{seed}", {"model": "i2s", "dataset": "modelnet10_limited"}, {"seed": seed},
                 accuracy_metrics(0.5, 0.6, 40.0, calibration_ece=ece))  # fmt: skip
    make_run(
        tmp_path, "r", {"model": "regression_6d", "dataset": "modelnet10_limited"}, {}, accuracy_metrics(0.1, 0.2, 60.0)
    )
    text = to_markdown(build_table("table6", LAYOUTS["table6"], find_runs([tmp_path])[0]))
    calibration = text.split("Calibration")[1]
    assert "| I2S | 0.030 ± 0.014 |" in calibration
    assert "| Zhou et al. 2019 (6D) | n/a |" in calibration
    assert "| Murphy et al. 2021 (IPDF) | — |" in calibration
    # a density's run without the calibration keys (written before they existed) is not "n/a"
    make_run(tmp_path, "old", {"model": "ipdf", "dataset": "modelnet10_limited"}, {},
             accuracy_metrics(0.1, 0.2, 60.0, log_likelihood=1.0))  # fmt: skip
    text = to_markdown(build_table("table6", LAYOUTS["table6"], find_runs([tmp_path])[0]))
    assert "| Murphy et al. 2021 (IPDF) | not recorded |" in text.split("Calibration")[1]


# ------------------------------------------------------------------------------- unfinished and hostile
def test_unfinished_and_broken_runs_are_reported_not_skipped(tmp_path, capsys):
    sweep = tmp_path / "sweep"
    make_run(
        sweep,
        "0",
        {"table": "table6", "model": "i2s", "dataset": "modelnet10_limited"},
        {},
        accuracy_metrics(0.6, 0.6, 40),
    )
    make_run(sweep, "1", {"table": "table6", "model": "ipdf", "dataset": "modelnet10_limited"}, {}, None)
    broken = make_run(
        sweep, "2", {"table": "table6", "model": "regression_6d", "dataset": "modelnet10_limited"}, {}, None
    )
    (broken / "metrics.json").write_text('{"acc15": 0.5,')  # truncated
    nan_text = make_run(
        sweep, "3", {"table": "table6", "model": "regression_9d", "dataset": "modelnet10_limited"}, {}, None
    )
    (nan_text / "metrics.json").write_text('{"acc15": "high"}')
    assert tables_main([str(sweep), "--out", str(tmp_path / "out")]) == 0
    captured = capsys.readouterr()
    for job, reason in (("1", "no metrics.json"), ("2", "not readable JSON"), ("3", "'acc15' is not a number")):
        assert re.search(rf"not finished: \S*sweep/{job}: .*{reason}", captured.err), (job, captured.err)
        assert re.search(rf"not finished: `\S*sweep/{job}`: .*{reason}", (tmp_path / "out" / "table6.md").read_text())
    lines = table_lines(captured.out)
    assert lines[("Murphy et al. 2021 (IPDF)", "ours")] == ["—", "—", "—"]  # unfinished: a missing cell
    assert lines[("I2S", "ours")] == ["0.600", "0.600", "40.0"]


def test_cli_prints_again_and_never_replaces_a_file_without_force(tmp_path, capsys):
    sweep = tmp_path / "sweep"
    make_run(sweep, "0", {"table": "table6", "model": "i2s", "dataset": "modelnet10_limited"}, {},
             accuracy_metrics(0.5, 0.6, 40))  # fmt: skip
    assert tables_main([str(sweep)]) == 0
    files = [sweep / "tables" / "table6.md", sweep / "tables" / "table6.tex"]  # Table 6 has no figure
    assert capsys.readouterr().out.endswith(f"\nwrote {files[0]}, {files[1]}\n")
    state = [(f.read_bytes(), f.stat().st_mtime_ns) for f in files]
    # again: the same table is printed, nothing is written (the figure's case: test_figures_...)
    assert tables_main([str(sweep)]) == 0
    again = capsys.readouterr().out
    assert again.startswith("### Table 6")
    assert again.endswith(f"\n{files[0]}, {files[1]}: up to date (the same as this table), not written again\n")
    assert [(f.read_bytes(), f.stat().st_mtime_ns) for f in files] == state
    files[0].write_text("my edits")
    assert tables_main([str(sweep)]) == 0
    printed = capsys.readouterr()
    assert printed.out.startswith("### Table 6") and f"warning: {files[0]} is out of date" in printed.err
    assert "--force" in printed.err and files[0].read_text() == "my edits"
    assert tables_main([str(sweep), "--force"]) == 0
    assert files[0].read_text().startswith("### Table 6")
    assert capsys.readouterr().out.endswith(f"\nreplaced {files[0]}\n{files[1]}: up to date (the same as this "
                                            "table), not written again\n")  # fmt: skip


def test_cli_errors_name_the_problem(tmp_path, capsys):
    assert tables_main([str(tmp_path / "nope")]) == 2
    assert "no such directory" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert tables_main([str(tmp_path / "empty")]) == 2
    assert "no run directory" in capsys.readouterr().err
    make_run(tmp_path / "manual", "0", {"model": "i2s", "dataset": "modelnet10"}, {}, accuracy_metrics(0.5, 0.6, 40))
    assert tables_main([str(tmp_path / "manual")]) == 2
    assert "--table" in capsys.readouterr().err
    assert tables_main([str(tmp_path / "manual"), "--table", "table1", "--out", str(tmp_path / "o")]) == 0
    assert table_lines(capsys.readouterr().out)[("I2S", "ours")] == ["0.500", "0.600", "40.0"]


def test_dataset_option_tabulates_a_run_on_other_data_and_says_so(tmp_path):
    make_run(tmp_path, "0", {"model": "i2s", "dataset": "symsol_rendered"}, {"lmax": 6}, accuracy_metrics(0.5, 0.6, 40))
    runs = find_runs([tmp_path])[0]
    assert not build_table("table7", LAYOUTS["table7"], runs).used
    filled = build_table("table7", LAYOUTS["table7"], runs, dataset="symsol_rendered")
    assert filled.cells[2][0].mean == 0.5
    assert any("not comparable" in n for n in filled.notes)


def test_help_documents_the_inputs():
    proc = subprocess.run(
        [sys.executable, "-m", "src.tables", "--help"], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    for word in ("RUN_DIR", "--table", "--dataset", "--out", "--force", "--wandb-project", "metrics.json", "table1"):
        assert word in proc.stdout, word


# ------------------------------------------------------------------------------- LaTeX
def _tex_rows(tex: str) -> list[str]:
    body = tex.split(r"\midrule", 1)[1].split(r"\bottomrule")[0]
    return [line for line in body.splitlines() if line.strip().endswith(r"\\")]


def test_latex_is_escaped_and_every_row_has_the_right_number_of_cells(tmp_path):
    layout = {
        "title": "50% & more_of #1",
        "caption": "costs $5 {maybe} ~ ^ \\ 100%",
        "columns": [
            {"id": "a", "title": "acc_15 %", "metric": "acc15", "better": "higher", "digits": 3, "group": "G&1"},
            {"id": "b", "title": "med", "metric": "median_error_deg", "better": "lower", "digits": 1, "group": "G&1"},
        ],
        "rows": [
            {"label": "A & B_2 (#1, 10%)", "match": {"model": "i2s"}, "published": {"a": 0.5, "b": 10.0}},
            {"label": "none", "match": {"model": "ipdf"}},
        ],
    }
    make_run(tmp_path, "0", {"model": "i2s"}, {}, accuracy_metrics(0.55, 0.6, 9.0))
    tex = to_latex(build_table("my_table", layout, find_runs([tmp_path])[0]))
    assert r"A \& B\_2 (\#1, 10\%)" in tex and r"acc\_15 \%" in tex and r"\multicolumn{2}{c}{G\&1}" in tex
    assert r"costs \$5 \{maybe\} \textasciitilde{} \textasciicircum{} \textbackslash{} 100\%" in tex
    assert r"\label{tab:my\_table}" in tex
    for line in _tex_rows(tex):
        unescaped = re.sub(r"\\.", "", line.replace(r"\\", ""))
        assert unescaped.count("&") == 3, line  # label, source, two columns
        assert unescaped.count("{") == unescaped.count("}"), line
        assert "%" not in unescaped and "_" not in unescaped and "#" not in unescaped, line
    assert r"0.550 & 9.0 \\" in tex and r"+0.050 & -1.0 \\" in tex
    assert r"none & ours & -- & -- \\" in tex
    assert tex.count(r"\begin{tabular}") == tex.count(r"\end{tabular}") == 1
    assert latex_escape("a\\b") == r"a\textbackslash{}b"


# ------------------------------------------------------------------------------- figures, wandb
def test_figures_line_and_bars_and_none_without_values(tmp_path):
    from PIL import Image

    for lmax, acc in ((2, 0.4), (6, 0.6)):
        make_run(tmp_path / "l", f"{lmax}", {"model": "i2s", "dataset": "modelnet10_limited"}, {"lmax": lmax},
                 accuracy_metrics(acc, acc, 40))  # fmt: skip
    png = draw_figure(build_table("table7", LAYOUTS["table7"], find_runs([tmp_path / "l"])[0]), tmp_path / "t7.png")
    assert png is not None and Image.open(png).size[0] > 500
    # drawn again, the same bytes: src.tables compares a new figure with the file to tell whether it is up to date
    again = draw_figure(build_table("table7", LAYOUTS["table7"], find_runs([tmp_path / "l"])[0]), tmp_path / "a.png")
    assert again.read_bytes() == png.read_bytes()
    make_run(
        tmp_path / "b",
        "0",
        {"model": "i2s", "dataset": "modelnet10"},
        {},
        accuracy_metrics(0.5, 0.5, 20, **{"median_error_deg/bed": 3.0}),
    )
    assert draw_figure(build_table("table5", LAYOUTS["table5"], find_runs([tmp_path / "b"])[0]), tmp_path / "t5.png")
    assert (
        draw_figure(build_table("table6", LAYOUTS["table6"], find_runs([tmp_path / "b"])[0]), tmp_path / "t6.png")
        is None
    )
    assert (
        draw_figure(build_table("table5", LAYOUTS["table5"], find_runs([tmp_path / "l"])[0]), tmp_path / "x.png")
        is None
    )
    assert not (tmp_path / "x.png").exists()


def test_push_to_wandb_offline(tmp_path, monkeypatch):
    monkeypatch.setenv("WANDB_SILENT", "true")
    make_run(tmp_path / "s", "0", {"table": "table7", "model": "i2s", "dataset": "modelnet10_limited"}, {"lmax": 2},
             accuracy_metrics(0.5, 0.6, 40))  # fmt: skip
    out = tmp_path / "out"
    assert tables_main([str(tmp_path / "s"), "--out", str(out), "--wandb-project", "tables-test"]) == 0
    runs = list((out / "wandb").glob("offline-run-*"))
    assert len(runs) == 1
    assert any(f.suffix == ".wandb" for f in runs[0].iterdir())
    table_files = list(runs[0].glob("files/media/table/*.table.json"))
    assert table_files, sorted(str(p) for p in runs[0].rglob("*"))
    data = json.loads(table_files[0].read_text())
    assert data["columns"][:3] == ["method", "source", "Acc@15"]
    assert ["L=2", "ours (1 run)", "0.500", "0.600", "40.0"] in data["data"]


# ------------------------------------------------------------------------------- layouts vs conf/table
def test_every_table_file_has_a_layout_and_rows_name_existing_models():
    tables = {p.stem for p in (REPO / "conf" / "table").glob("*.yaml")}
    # the paper's tables, and layouts of our own for a small sweep: small_<name> for table=small/<name>
    small = {f"small_{p.stem}" for p in (REPO / "conf" / "table" / "small").glob("*.yaml")}
    assert tables <= set(LAYOUTS) and set(LAYOUTS) - tables <= small, set(LAYOUTS) ^ tables
    models = {p.stem for p in (REPO / "conf" / "model").glob("*.yaml")}
    for name, layout in LAYOUTS.items():
        for row in layout["rows"]:
            model = {**(layout.get("match") or {}), **row["match"]}.get("model")
            assert model in models, (name, row["label"])
            assert not math.isnan(sum(row["published"].values()))


def test_layout_errors_name_the_table_and_entry(tmp_path):
    bad = {"t": {"title": "x", "columns": [{"id": "a", "title": "A", "metric": "acc15", "better": "up"}], "rows": []}}
    path = tmp_path / "layouts.yaml"
    path.write_text(yaml.safe_dump(bad))
    with pytest.raises(ValueError, match="t: column 'a': better must be higher or lower"):
        load_layouts(path)
    bad["t"]["columns"][0]["better"] = "higher"
    bad["t"]["rows"] = [{"label": "r", "match": {}, "published": {"zz": 1.0}}]
    path.write_text(yaml.safe_dump(bad))
    with pytest.raises(ValueError, match=r"row 'r': published values for unknown columns \['zz'\]"):
        load_layouts(path)


def test_wandb_project_defaults_to_the_runs_own(tmp_path, monkeypatch):
    import wandb

    calls = []

    class FakeRun:
        def log(self, data):
            calls.append(("log", sorted(data)))

        def finish(self):
            calls.append(("finish",))

    monkeypatch.setattr(wandb, "init", lambda **kw: calls.append(("init", kw)) or FakeRun())
    config = {"logger": {"wandb": {"project": "my-sweeps", "entity": "lab"}}}
    make_run(tmp_path / "p", "0", {"table": "table6", "model": "i2s", "dataset": "modelnet10_limited"}, config,
             accuracy_metrics(0.5, 0.6, 40))  # fmt: skip
    assert tables_main([str(tmp_path / "p"), "--out", str(tmp_path / "o1"), "--wandb-project"]) == 0
    init = calls[0][1]
    assert (init["project"], init["entity"], init["mode"], init["name"]) == ("my-sweeps", "lab", "offline", "table6")
    assert calls[1] == ("log", ["table6", "table6_markdown"]) and calls[2] == ("finish",)
    calls.clear()
    assert tables_main([str(tmp_path / "p"), "--out", str(tmp_path / "o2"), "--wandb-project", "other"]) == 0
    assert calls[0][1]["project"] == "other"
    calls.clear()
    assert tables_main([str(tmp_path / "p"), "--out", str(tmp_path / "o3")]) == 0
    assert not calls  # no wandb unless asked


def test_a_smoke_run_is_not_counted_unless_asked_and_then_marked(tmp_path, capsys):
    sweep = tmp_path / "sweep"
    choices = {"table": "table6", "model": "i2s", "dataset": "modelnet10_limited"}
    make_run(sweep, "0", choices, {}, accuracy_metrics(0.5, 0.6, 40))
    smoke_config = {"seed": 1, "trainer": {"fast_dev_run": True}}
    smoke = make_run(sweep, "1", choices, smoke_config, accuracy_metrics(0.1, 0.2, 90))
    assert tables_main([str(sweep), "--out", str(tmp_path / "a")]) == 0
    printed = capsys.readouterr()
    assert table_lines(printed.out)[("I2S", "ours")] == ["0.500", "0.600", "40.0"]
    assert "| I2S | ours (1 run) |" in printed.out and f"- not counted: `{smoke}` (fast_dev_run)" in printed.out
    assert f"not counted: {smoke} (fast_dev_run)" in printed.err.splitlines()
    assert tables_main([str(sweep), "--out", str(tmp_path / "b"), "--include-unfinished"]) == 0
    printed = capsys.readouterr()
    assert table_lines(printed.out)[("I2S", "ours")] == ["0.300 ± 0.283", "0.400 ± 0.283", "65.0 ± 35.4"]
    assert "| I2S | ours (2 runs, 1 unfinished) |" in printed.out
    assert f"- counted although unfinished: `{smoke}` (fast_dev_run)" in printed.out
    assert "1 of the runs are trainer.fast_dev_run smoke tests" in printed.out
