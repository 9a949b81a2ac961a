"""``python -m src.tables`` on a sweep that is none of the paper's tables: one row per setting, the
overrides that differ as columns, the headline metrics as mean ± sample std over seeds; an Optuna
study's trials ordered by its objective; unfinished runs listed; never overwriting a table written.

The run directories are written by hand with the files and layout a real ``python -m src.train -m``
job leaves (``.hydra/config.yaml``, ``hydra.yaml``, ``overrides.yaml``, ``metrics.json``); the slow
test runs a real sweep and tabulates it."""

from __future__ import annotations

import json
import re
import statistics
import sys
import types
from pathlib import Path

import pytest
import yaml
from src.tables import main as tables_main

from image2sphere.reporting import build_sweep_table, find_runs, sweep_to_markdown

CLASSES = ("cube", "cone")
# the part of a composed config (as .hydra/config.yaml holds it) that these runs read or override
BASE_CONFIG = {
    "task_name": "train",
    "tags": ["dev"],
    "seed": 0,
    "optimized_metric": "log_likelihood",
    "lmax": 6,
    "train_grid_level": 3,
    "eval_grid_level": 5,
    "model": {
        "net": {"lmax": "${lmax}", "sphere_channels": 512, "so3_channels": 16},
        "optimizer": {"lr": 0.001, "weight_decay": 0.0},
    },
    "trainer": {"max_epochs": 5, "fast_dev_run": False},
    "logger": {},
}
CHOICES = {"table": None, "hparams_search": None, "dataset": "symsol_rendered", "model": "i2s", "encoder": "resnet18",
           "logger": "none", "hydra/sweeper": "basic"}  # fmt: skip


def metrics_of(ll: float, spread: float, ece: float, acc15: float, acc30: float, median: float, **extra) -> dict:
    """A metrics.json as src.train writes it: the class means, and per-class values that differ from them."""
    means = {"log_likelihood": ll, "spread_deg": spread, "calibration_ece": ece, "acc15": acc15, "acc30": acc30,
             "median_error_deg": median}  # fmt: skip
    out = {"loss": 10.0, "n_images": 6.0, "test_seconds": 0.5, "train_seconds": 1.0, "hdr_coverage_50": 0.5}
    for key, value in means.items():
        out[key] = value
        out[f"{key}/cube"], out[f"{key}/cone"] = value + 100.0, value - 100.0  # never the class mean
    return {**out, **extra}


def _set(config: dict, key: str, value) -> None:
    *parents, last = key.lstrip("+").split(".")
    node = config
    for part in parents:
        node = node.setdefault(part, {})
    node[last] = value


def write_run(sweep: Path, job: int, overrides: list[str], metrics: dict | None, sweeper: dict | None = None) -> Path:
    """Job ``job`` of a multirun under ``sweep``, launched with ``overrides``; ``metrics=None``: not finished."""
    run = sweep / str(job)
    (run / ".hydra").mkdir(parents=True)
    config = json.loads(json.dumps(BASE_CONFIG))
    choices = dict(CHOICES)
    for override in overrides:
        key, value = override.split("=", 1)
        if key.lstrip("+") in choices:
            choices[key.lstrip("+")] = value
        else:
            _set(config, key, yaml.safe_load(value))
    hydra = {
        "hydra": {
            "sweep": {"dir": str(sweep), "subdir": "${hydra.job.num}"},
            "sweeper": sweeper or {"_target_": "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"},
            "mode": "MULTIRUN",
            "overrides": {"hydra": ["hydra.mode=MULTIRUN"], "task": overrides},
            "job": {"name": "train", "num": job, "override_dirname": ",".join(sorted(overrides))},
            "runtime": {"output_dir": str(run), "choices": choices},
        }
    }
    (run / ".hydra" / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    (run / ".hydra" / "hydra.yaml").write_text(yaml.safe_dump(hydra, sort_keys=False))
    (run / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    if metrics is not None:
        (run / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return run


def table_rows(markdown: str, title: str | None = None) -> list[dict[str, str]]:
    """The rows of the first Markdown table (or of the one under the line ``<title>:``), as ``column title -> cell``."""
    text = markdown.split(f"\n{title}:\n", 1)[1] if title else markdown
    lines = []
    for line in text.splitlines():
        if line.startswith("| "):
            lines.append(line)
        elif lines and not line.startswith("|"):
            break  # the end of the table
    header = [c.strip() for c in lines[0].strip().strip("|").split("|")]
    return [dict(zip(header, [c.strip() for c in line.strip().strip("|").split("|")], strict=True))
            for line in lines[1:]]  # fmt: skip


def mean_pm_std(values: list[float], digits: int) -> str:
    return f"{statistics.mean(values):.{digits}f} ± {statistics.stdev(values):.{digits}f}"


# ------------------------------------------------------------------------------------- settings x seeds
def test_two_settings_two_seeds_mean_and_sample_std(tmp_path, capsys):
    sweep = tmp_path / "multiruns" / "2026-01-01_00-00-00_1"
    values = {  # (lmax, seed) -> ll, spread, ece, acc15, acc30, median
        (2, 0): (-1.25, 40.0, 0.10, 0.20, 0.40, 50.0),
        (2, 1): (-0.75, 44.0, 0.05, 0.30, 0.50, 30.0),
        (4, 0): (2.5, 20.0, 0.02, 0.60, 0.70, 12.0),
        (4, 1): (3.25, 22.5, 0.04, 0.65, 0.80, 9.5),
    }
    for job, ((lmax, seed), v) in enumerate(values.items()):
        write_run(sweep, job, [f"lmax={lmax}", f"seed={seed}", "trainer.max_epochs=1", "logger=none"], metrics_of(*v))
    out = tmp_path / "out"
    assert tables_main([str(sweep), "--out", str(out)]) == 0
    printed = capsys.readouterr()
    rows = table_rows(printed.out)
    # seed is averaged over; trainer.max_epochs and logger are the same in every run: no columns
    assert list(rows[0]) == ["lmax", "log lik.", "spread", "ECE", "acc@15", "acc@30", "med.err", "runs"]
    assert [r["lmax"] for r in rows] == ["2", "4"] and [r["runs"] for r in rows] == ["2", "2"]
    digits = {"log lik.": 3, "spread": 2, "ECE": 3, "acc@15": 3, "acc@30": 3, "med.err": 2}
    for row, lmax in zip(rows, (2, 4), strict=True):
        for j, (title, d) in enumerate(digits.items()):
            seeds = [values[(lmax, s)][j] for s in (0, 1)]
            assert row[title] == mean_pm_std(seeds, d), (lmax, title, row)
    # the numbers by hand, once: lmax 2's log likelihood is -1.0 ± 0.354 (sqrt(0.125))
    assert rows[0]["log lik."] == "-1.000 ± 0.354" and rows[1]["med.err"] == "10.75 ± 1.77"
    assert (out / "sweep.md").read_text() in printed.out and (out / "sweep.tex").is_file()
    assert "--table" in printed.err and "not finished" not in printed.out + printed.err


def test_a_single_run_per_setting_has_no_spread_and_a_missing_metric_is_na(tmp_path):
    sweep = tmp_path / "s"
    write_run(sweep, 0, ["model=i2s"], metrics_of(1.0, 10.0, 0.1, 0.5, 0.6, 20.0))
    point = {k: v for k, v in metrics_of(0.0, 0.0, 0.0, 0.4, 0.5, 25.0).items() if not k.startswith(
        ("log_likelihood", "spread", "calibration"))}  # fmt: skip
    write_run(sweep, 1, ["model=regression_6d"], point)
    rows = table_rows(sweep_to_markdown(build_sweep_table(find_runs([sweep])[0])))
    assert rows[0] == {"model": "i2s", "log lik.": "1.000", "spread": "10.00", "ECE": "0.100", "acc@15": "0.500",
                       "acc@30": "0.600", "med.err": "20.00", "runs": "1"}  # fmt: skip
    assert rows[1]["log lik."] == "n/a" and rows[1]["ECE"] == "n/a" and rows[1]["acc@15"] == "0.400"


def test_only_seeds_differ_gives_one_row_of_all_runs(tmp_path):
    sweep = tmp_path / "s"
    for seed, ll in enumerate((1.0, 2.0, 4.0)):
        write_run(sweep, seed, [f"seed={seed}"], metrics_of(ll, 10.0, 0.1, 0.5, 0.6, 20.0))
    (row,) = table_rows(sweep_to_markdown(build_sweep_table(find_runs([sweep])[0])))
    assert row["setting"] == "all runs" and row["runs"] == "3"
    assert row["log lik."] == mean_pm_std([1.0, 2.0, 4.0], 3)


# ------------------------------------------------------------------------------------- unfinished, keys
def test_an_unfinished_run_is_listed_below_the_table(tmp_path, capsys):
    sweep = tmp_path / "s"
    write_run(sweep, 0, ["lmax=2"], metrics_of(1.0, 10.0, 0.1, 0.5, 0.6, 20.0))
    write_run(sweep, 1, ["lmax=4"], metrics_of(2.0, 10.0, 0.1, 0.5, 0.6, 20.0))
    write_run(sweep, 2, ["lmax=8"], None)
    assert tables_main([str(sweep), "--out", str(tmp_path / "out")]) == 0
    printed = capsys.readouterr()
    assert [r["lmax"] for r in table_rows(printed.out)] == ["2", "4"]
    assert re.search(r"- not finished: `\S*/s/2`: no metrics.json", printed.out)
    assert re.search(r"not finished: \S*/s/2: no metrics.json", printed.err)
    assert "not finished: `" in (tmp_path / "out" / "sweep.md").read_text()


def test_a_key_in_only_some_runs_shows_the_composed_value_or_a_dash(tmp_path):
    sweep = tmp_path / "s"
    write_run(sweep, 0, ["lmax=2"], metrics_of(1.0, 10.0, 0.1, 0.5, 0.6, 20.0))
    write_run(
        sweep, 1, ["lmax=2", "encoder=resnet34", "model.optimizer.lr=0.01"], metrics_of(2.0, 9, 0.1, 0.5, 0.6, 20)
    )
    write_run(sweep, 2, ["lmax=4", "+model.net.extra=7"], metrics_of(3.0, 8.0, 0.1, 0.5, 0.6, 20.0))
    # set on the command line, but to what every other run composes to: the same everywhere, no column
    write_run(sweep, 3, ["lmax=4", "train_grid_level=3"], metrics_of(4.0, 7.0, 0.1, 0.5, 0.6, 20.0))
    rows = table_rows(sweep_to_markdown(build_sweep_table(find_runs([sweep])[0])))
    keys = ["lmax", "encoder", "model.optimizer.lr", "model.net.extra"]
    assert list(rows[0])[: len(keys) + 1] == [*keys, "log lik."]
    assert [[r[k] for k in keys] for r in rows] == [
        ["2", "resnet18", "0.001", "—"],  # the group's choice and the config's value where not overridden
        ["2", "resnet34", "0.01", "—"],
        ["4", "resnet18", "0.001", "7"],
        ["4", "resnet18", "0.001", "—"],
    ]
    assert "train_grid_level" not in rows[0]  # set to 3 in one run, composed to 3 in the others
    assert [r["runs"] for r in rows] == ["1", "1", "1", "1"]


def test_a_key_set_to_the_composed_value_is_the_same_setting(tmp_path):
    sweep = tmp_path / "s"
    write_run(sweep, 0, ["lmax=6", "seed=0"], metrics_of(1.0, 10.0, 0.1, 0.5, 0.6, 20.0))
    write_run(sweep, 1, ["seed=1"], metrics_of(2.0, 10.0, 0.1, 0.5, 0.6, 20.0))  # lmax 6 composed
    write_run(sweep, 2, ["lmax=2", "seed=0"], metrics_of(5.0, 10.0, 0.1, 0.5, 0.6, 20.0))
    rows = table_rows(sweep_to_markdown(build_sweep_table(find_runs([sweep])[0])))
    assert [(r["lmax"], r["runs"], r["log lik."]) for r in rows] == [("6", "2", "1.500 ± 0.707"), ("2", "1", "5.000")]


def test_calibrated_metrics_get_columns_only_where_metrics_json_has_them(tmp_path):
    sweep = tmp_path / "s"
    # as a run that fitted a recalibration writes them: every HDR coverage has a twin too, which is no column
    extra = {"log_likelihood_calibrated": 1.5, "calibration_ece_calibrated": 0.01, "log_likelihood_calibrated/cube": 9,
             "hdr_coverage_50_calibrated": 0.5, "temperature": 1.2}  # fmt: skip
    write_run(sweep, 0, ["lmax=2"], metrics_of(1.0, 10.0, 0.1, 0.5, 0.6, 20.0, **extra))
    write_run(sweep, 1, ["lmax=4"], metrics_of(2.0, 10.0, 0.2, 0.5, 0.6, 20.0))
    markdown = sweep_to_markdown(build_sweep_table(find_runs([sweep])[0]))
    rows = table_rows(markdown)
    # the titles of the per-run table (src.train's), right after the metric they recalibrate
    assert list(rows[0]) == ["lmax", "log lik.", "LL recal.", "spread", "ECE", "ECE recal.", "acc@15", "acc@30",
                             "med.err", "runs"]  # fmt: skip
    assert (rows[0]["LL recal."], rows[0]["ECE recal."]) == ("1.500", "0.010")
    assert (rows[1]["LL recal."], rows[1]["ECE recal."]) == ("n/a", "n/a")
    assert "LL recal., ECE recal.: after recalibration" in markdown
    (tmp_path / "t").mkdir()
    write_run(tmp_path / "t", 0, ["lmax=2"], metrics_of(1.0, 10.0, 0.1, 0.5, 0.6, 20.0))
    write_run(tmp_path / "t", 1, ["lmax=4"], metrics_of(1.0, 10.0, 0.1, 0.5, 0.6, 20.0))
    assert "recal" not in sweep_to_markdown(build_sweep_table(find_runs([tmp_path / "t"])[0]))


def test_a_further_metric_is_one_entry_of_the_column_list(tmp_path, monkeypatch):
    from image2sphere.reporting import sweep_table

    monkeypatch.setattr(sweep_table, "SWEEP_METRICS", (*sweep_table.SWEEP_METRICS, ("temperature", "T", "{:.2f}")))
    sweep = tmp_path / "s"
    write_run(sweep, 0, ["lmax=2"], metrics_of(1.0, 10.0, 0.1, 0.5, 0.6, 20.0, temperature=1.25))
    write_run(sweep, 1, ["lmax=4"], metrics_of(2.0, 10.0, 0.2, 0.5, 0.6, 20.0))
    rows = table_rows(sweep_to_markdown(build_sweep_table(find_runs([sweep])[0])))
    assert [(r["lmax"], r["T"]) for r in rows] == [("2", "1.25"), ("4", "n/a")]


# ------------------------------------------------------------------------------------- Optuna
OPTUNA = "hydra_plugins.hydra_optuna_sweeper.optuna_sweeper.OptunaSweeper"


@pytest.mark.parametrize("direction", ["maximize", "minimize"])
def test_an_optuna_study_is_ordered_by_its_objective_best_first(tmp_path, direction, capsys):
    sweep = tmp_path / "optuna"
    sweeper = {"_target_": OPTUNA, "direction": direction, "study_name": "optuna_i2s", "n_trials": 4}
    trials = [(0.0012520653814999472, 4, -2.0), (0.00075, 2, 1.5), (0.004, 6, 0.25), (0.0001, 8, -0.5)]
    for job, (lr, lmax, ll) in enumerate(trials):
        overrides = [f"model.optimizer.lr={lr}", f"lmax={lmax}", "hparams_search=optuna_i2s"]
        write_run(sweep, job, overrides, metrics_of(ll, 10.0, 0.1, 0.5, 0.6, 20.0), sweeper)
    best = max(ll for *_, ll in trials) if direction == "maximize" else min(ll for *_, ll in trials)
    (sweep / "optimization_results.yaml").write_text(yaml.safe_dump({"name": "optuna", "best_value": best}))
    assert tables_main([str(sweep), "--out", str(tmp_path / "out")]) == 0
    printed = capsys.readouterr().out
    rows = table_rows(printed)
    arrow = "↑" if direction == "maximize" else "↓"
    assert list(rows[0]) == ["model.optimizer.lr", "lmax", f"log lik. (objective {arrow})", "spread", "ECE",
                             "acc@15", "acc@30", "med.err", "runs"]  # fmt: skip
    order = sorted(trials, key=lambda t: -t[2] if direction == "maximize" else t[2])
    assert [r["lmax"] for r in rows] == [str(t[1]) for t in order]
    assert [r[f"log lik. (objective {arrow})"] for r in rows] == [f"{t[2]:.3f}" for t in order]
    assert "0.00125207" in [r["model.optimizer.lr"] for r in rows]  # a sampler's float, to 6 digits
    assert "Optuna study optuna_i2s" in printed and f"({direction}), best first" in printed
    assert f"optimization_results.yaml`: {best}" in printed


def test_an_objective_that_is_no_column_is_added_and_a_basic_sweep_keeps_job_order(tmp_path):
    sweep = tmp_path / "optuna"
    sweeper = {"_target_": OPTUNA, "direction": ["minimize"], "study_name": "s"}
    for job, loss in enumerate((3.0, 1.0, 2.0)):
        write_run(sweep, job, [f"lmax={2 * job + 2}", "optimized_metric=loss"],
                  {**metrics_of(0.0, 10.0, 0.1, 0.5, 0.6, 20.0), "loss": loss}, sweeper)  # fmt: skip
    rows = table_rows(sweep_to_markdown(build_sweep_table(find_runs([sweep])[0])))
    assert [(r["lmax"], r["loss (objective ↓)"]) for r in rows] == [("4", "1.000"), ("6", "2.000"), ("2", "3.000")]
    basic = tmp_path / "basic"  # no direction: the order of the jobs (10 after 9), not of the metric
    for job in range(11):
        write_run(basic, job, [f"lmax={job}"], metrics_of(float(-job), 10.0, 0.1, 0.5, 0.6, 20.0))
    rows = table_rows(sweep_to_markdown(build_sweep_table(find_runs([basic])[0])))
    assert [r["lmax"] for r in rows] == [str(j) for j in range(11)]


# ------------------------------------------------------------------------------------- files, errors
def _files_state(*paths: Path) -> list[tuple[bytes, int]]:
    return [(p.read_bytes(), p.stat().st_mtime_ns) for p in paths]


def test_a_second_run_prints_the_table_again_and_never_replaces_a_file_without_force(tmp_path, capsys):
    sweep = tmp_path / "s"
    write_run(sweep, 0, ["lmax=2"], metrics_of(1.0, 10.0, 0.1, 0.5, 0.6, 20.0))
    write_run(sweep, 1, ["lmax=4"], metrics_of(2.0, 10.0, 0.1, 0.5, 0.6, 20.0))
    md, tex = sweep / "tables" / "sweep.md", sweep / "tables" / "sweep.tex"
    assert tables_main([str(sweep)]) == 0
    first = capsys.readouterr()
    assert first.out.startswith("### Sweep: 2 finished runs, 2 settings")
    assert first.out.endswith(f"\nwrote {md}, {tex}\n") and "out of date" not in first.err
    written = _files_state(md, tex)

    # the same runs again: the same table printed, the files left alone, one line saying so
    assert tables_main([str(sweep)]) == 0
    second = capsys.readouterr()
    table = first.out.rsplit("\nwrote ", 1)[0]
    assert second.out == f"{table}\n{md}, {tex}: up to date (the same as this table), not written again\n"
    assert second.err == first.err and _files_state(md, tex) == written

    # a run finished since: the new table is printed, the files are out of date and left as they are
    write_run(sweep, 2, ["lmax=8"], metrics_of(3.0, 10.0, 0.1, 0.5, 0.6, 20.0))
    assert tables_main([str(sweep)]) == 0
    third = capsys.readouterr()
    assert [r["lmax"] for r in table_rows(third.out)] == ["2", "4", "8"]
    assert "wrote" not in third.out and "up to date" not in third.out
    (line,) = [line for line in third.err.splitlines() if "out of date" in line]
    assert line == (f"warning: {md}, {tex} are out of date (runs finished or changed since, or the file was edited); "
                    "nothing was written: pass --force to replace, or --out <another folder>")  # fmt: skip
    assert _files_state(md, tex) == written

    # --force replaces them with the table printed; a missing file is written without it, the others kept
    assert tables_main([str(sweep), "--force"]) == 0
    forced = capsys.readouterr()
    assert forced.out.endswith(f"\nreplaced {md}, {tex}\n") and md.read_text() in forced.out
    tex.unlink()
    kept = _files_state(md)
    assert tables_main([str(sweep)]) == 0
    up_to_date = f"{md}: up to date (the same as this table), not written again"
    assert capsys.readouterr().out.endswith(f"\nwrote {tex}\n{up_to_date}\n")
    assert _files_state(md) == kept and tex.is_file()


def test_an_edited_file_is_out_of_date_and_kept(tmp_path, capsys):
    sweep = tmp_path / "s"
    write_run(sweep, 0, ["lmax=2"], metrics_of(1.0, 10.0, 0.1, 0.5, 0.6, 20.0))
    write_run(sweep, 1, ["lmax=4"], metrics_of(2.0, 10.0, 0.1, 0.5, 0.6, 20.0))
    assert tables_main([str(sweep)]) == 0
    md, tex = sweep / "tables" / "sweep.md", sweep / "tables" / "sweep.tex"
    md.write_text("my edits")
    tex.unlink()  # missing beside an out-of-date file: not written either, the set stays as it was
    capsys.readouterr()
    assert tables_main([str(sweep)]) == 0
    printed = capsys.readouterr()
    assert "### Sweep" in printed.out and f"warning: {md} is out of date" in printed.err
    assert md.read_text() == "my edits" and not tex.exists()


def test_a_single_run_that_is_no_sweep_job_is_still_refused(tmp_path, capsys):
    run = write_run(tmp_path / "runs", 0, ["lmax=2"], metrics_of(1.0, 10.0, 0.1, 0.5, 0.6, 20.0))
    hydra = yaml.safe_load((run / ".hydra" / "hydra.yaml").read_text())
    hydra["hydra"]["mode"] = "RUN"
    (run / ".hydra" / "hydra.yaml").write_text(yaml.safe_dump(hydra))
    assert tables_main([str(run)]) == 2
    assert "--table" in capsys.readouterr().err
    hydra["hydra"]["mode"] = "MULTIRUN"  # the only job of a sweep: its table of one row
    (run / ".hydra" / "hydra.yaml").write_text(yaml.safe_dump(hydra))
    assert tables_main([str(run), "--out", str(tmp_path / "o")]) == 0


def _tex_rows(tex: str) -> list[str]:
    body = tex.split(r"\midrule", 1)[1].split(r"\bottomrule")[0]
    return [line for line in body.splitlines() if line.strip().endswith(r"\\")]


def test_latex_output_is_escaped_and_every_row_has_every_cell(tmp_path):
    sweep = tmp_path / "s"
    sweeper = {"_target_": OPTUNA, "direction": "maximize", "study_name": "my_study"}
    write_run(sweep, 0, ["model.optimizer.weight_decay=0.0", "seed=0", "+my_key=a_b"],
              metrics_of(1.0, 10.0, 0.1, 0.5, 0.6, 20.0), sweeper)  # fmt: skip
    write_run(sweep, 1, ["model.optimizer.weight_decay=0.0", "seed=1", "+my_key=a_b"],
              metrics_of(2.0, 12.0, 0.2, 0.5, 0.6, 20.0), sweeper)  # fmt: skip
    write_run(
        sweep, 2, ["model.optimizer.weight_decay=1e-05", "seed=0"], metrics_of(0.5, 10, 0.1, 0.5, 0.6, 20), sweeper
    )
    assert tables_main([str(sweep), "--out", str(tmp_path / "out")]) == 0
    tex = (tmp_path / "out" / "sweep.tex").read_text()
    assert r"\caption{Optuna study my\_study: 3 finished runs, 2 settings." in tex and r"\label{tab:sweep}" in tex
    assert r"\begin{tabular}{llrrrrrrr}" in tex
    header = tex.split(r"\toprule", 1)[1].split(r"\midrule")[0].strip()
    assert header.startswith(r"model.optimizer.weight\_decay & my\_key & log lik. (objective $\uparrow$) & spread")
    rows = _tex_rows(tex)
    assert rows[0] == r"0.0 & a\_b & 1.500 $\pm$ 0.707 & 11.00 $\pm$ 1.41 & 0.150 $\pm$ 0.071 & 0.500 $\pm$ 0.000 & " \
        r"0.600 $\pm$ 0.000 & 20.00 $\pm$ 0.00 & 2 \\"  # fmt: skip
    assert rows[1].startswith(r"1e-05 & -- & 0.500 & ")  # absent key: --
    for line in [header, *rows]:
        unescaped = re.sub(r"\\.", "", line.replace(r"\\", ""))
        assert unescaped.count("&") == 8, line  # two keys, six metrics, runs
        assert "_" not in unescaped and "±" not in line and "—" not in line, line
    # the tables of the further metrics each have their own tabular: numbers and timings, the HDR coverage
    assert tex.count(r"\begin{tabular}") == tex.count(r"\end{tabular}") == 3
    assert r"\label{tab:sweep-1}" in tex and r"\label{tab:sweep-2}" in tex and r"& 50\% \\" in tex


def test_wandb_gets_the_sweep_table(tmp_path, monkeypatch):
    calls = []

    class FakeRun:
        def log(self, data):
            calls.append(("log", data))

        def finish(self):
            calls.append(("finish",))

    fake = types.ModuleType("wandb")  # wandb's own API, recorded (importing the real one takes a second)
    fake.init = lambda **kw: calls.append(("init", kw)) or FakeRun()
    fake.Table = lambda columns, data: ("table", columns, data)
    fake.Html = lambda text: ("html", text)
    monkeypatch.setitem(sys.modules, "wandb", fake)
    sweep = tmp_path / "s"
    for job, lmax in enumerate((2, 4)):
        write_run(sweep, job, [f"lmax={lmax}", "+logger.wandb.project=my-sweeps"],
                  metrics_of(float(lmax), 10.0, 0.1, 0.5, 0.6, 20.0))  # fmt: skip
    assert tables_main([str(sweep), "--out", str(tmp_path / "o"), "--wandb-project"]) == 0
    init = calls[0][1]
    assert (init["project"], init["name"], init["job_type"], init["mode"]) == ("my-sweeps", "sweep", "sweep-table",
                                                                               "offline")  # fmt: skip
    logged = calls[1][1]
    assert sorted(logged) == ["sweep", "sweep_markdown"] and calls[2] == ("finish",)
    _, columns, data = logged["sweep"]
    assert columns[:2] == ["lmax", "log lik."] and columns[-1] == "runs"
    assert data == [["2", "2.000", "10.00", "0.100", "0.500", "0.600", "20.00", "1"],
                    ["4", "4.000", "10.00", "0.100", "0.500", "0.600", "20.00", "1"]]  # fmt: skip


# ------------------------------------------------------------------------------------- a real sweep
@pytest.mark.slow
def test_a_real_sweep_is_tabulated(tmp_path):
    """The acceptance commands, on the tiny built-in data: a sweep of lmax 2 and 4 (one epoch of two
    batches each), then ``src.tables`` on its directory prints each run's log likelihood."""
    from conftest import run_module, run_train

    command = ["-m", "lmax=2,4", "trainer.max_epochs=1", "trainer.limit_train_batches=2",
               "trainer.limit_val_batches=1", "logger=none"]  # fmt: skip
    run_train(command, tmp_path / "data", tmp_path / "logs")
    (sweep,) = (tmp_path / "logs" / "train" / "multiruns").iterdir()
    proc = run_module([sys.executable, "-m", "src.tables", str(sweep)])
    rows = table_rows(proc.stdout)
    assert [r["lmax"] for r in rows] == ["2", "4"] and [r["runs"] for r in rows] == ["1", "1"], proc.stdout
    jobs = {yaml.safe_load((j / ".hydra" / "config.yaml").read_text())["lmax"]: j for j in sweep.glob("[0-9]*")}
    assert sorted(jobs) == [2, 4]
    for row in rows:
        job = jobs[int(row["lmax"])]
        metrics = json.loads((job / "metrics.json").read_text())
        assert row["log lik."] == f"{metrics['log_likelihood']:.3f}", (row, metrics["log_likelihood"])
        assert row["med.err"] == f"{metrics['median_error_deg']:.2f}"
    assert "not finished" not in proc.stdout + proc.stderr
    assert (sweep / "tables" / "sweep.md").read_text() in proc.stdout and (sweep / "tables" / "sweep.tex").is_file()


# ------------------------------------------------------------------------------------- every metric, the sweep's end
def test_a_method_s_own_metric_is_a_column_and_timings_are_under_the_table(tmp_path):
    """rotation_flow's log_likelihood_exact (and a metric of one's own) get columns after the headline ones,
    n/a for the run without them; the timings, loss and HDR coverage are in tables of their own below."""
    sweep = tmp_path / "s"
    write_run(sweep, 0, ["model=rotation_flow"], metrics_of(1.0, 10.0, 0.1, 0.5, 0.6, 20.0, log_likelihood_exact=1.25,
                                                           my_score=3.0))  # fmt: skip
    write_run(sweep, 1, ["model=i2s"], metrics_of(2.0, 10.0, 0.2, 0.5, 0.6, 20.0, recalibration_seconds=0.25))
    markdown = sweep_to_markdown(build_sweep_table(find_runs([sweep])[0]))
    rows = table_rows(markdown)
    assert list(rows[0]) == ["model", "log lik.", "spread", "ECE", "acc@15", "acc@30", "med.err", "LL exact",
                             "my_score", "runs"]  # fmt: skip
    assert [(r["model"], r["LL exact"], r["my_score"]) for r in rows] == [("rotation_flow", "1.250", "3.000"),
                                                                         ("i2s", "n/a", "n/a")]  # fmt: skip
    further = table_rows(markdown, "Further numbers (test loss, temperature, test images; wall times in seconds)")
    assert further == [
        {"model": "rotation_flow", "loss": "10.000", "test images": "6", "train (s)": "1.0", "recalibration (s)": "n/a",
         "test (s)": "0.5"},
        {"model": "i2s", "loss": "10.000", "test images": "6", "train (s)": "1.0", "recalibration (s)": "0.2",
         "test (s)": "0.5"},
    ]  # fmt: skip
    title = next(line[:-1] for line in markdown.splitlines() if line.startswith("HDR coverage"))
    coverage = table_rows(markdown, title)
    assert [(r["model"], r["50%"]) for r in coverage] == [("rotation_flow", "0.500"), ("i2s", "0.500")]


def test_a_sweep_ends_with_its_tables_command(tmp_path, monkeypatch, capsys):
    """The Hydra callback of conf/hydra/default.yaml, called as Hydra calls it when a multirun has ended: one
    line naming the sweep's directory (relative to where src.train ran), which src.tables then reads."""
    from omegaconf import OmegaConf

    from image2sphere.training.hydra_callbacks import PrintSweepTableCommand

    sweep = tmp_path / "logs" / "train" / "multiruns" / "2026-01-01_00-00-00_1"
    write_run(sweep, 0, ["lmax=2"], metrics_of(1.0, 10.0, 0.1, 0.5, 0.6, 20.0))
    write_run(sweep, 1, ["lmax=4"], metrics_of(2.0, 10.0, 0.1, 0.5, 0.6, 20.0))
    for name in ("RANK", "LOCAL_RANK", "NODE_RANK", "GROUP_RANK", "SLURM_NTASKS", "SLURM_PROCID"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.chdir(tmp_path)

    def config(job: str = "train", directory: str = "${paths.log_dir}/train/multiruns/2026-01-01_00-00-00_1"):
        return OmegaConf.create({"paths": {"log_dir": str(tmp_path / "logs")},
                                 "hydra": {"sweep": {"dir": directory}, "job": {"name": job}}})  # fmt: skip

    callback = PrintSweepTableCommand()
    callback.on_multirun_end(config())
    printed = capsys.readouterr()
    assert printed.out == "Table of this sweep: python -m src.tables logs/train/multiruns/2026-01-01_00-00-00_1\n"
    assert printed.err == ""
    command = printed.out.split("python -m src.tables ")[1].split()
    assert tables_main(command) == 0 and "### Sweep: 2 finished runs, 2 settings" in capsys.readouterr().out
    # a sweep of src.eval, a DDP rank other than 0, a sweep that wrote no directory: no line
    callback.on_multirun_end(config(job="eval"))
    callback.on_multirun_end(config(directory=str(tmp_path / "never_made")))
    monkeypatch.setenv("LOCAL_RANK", "1")
    callback.on_multirun_end(config())
    assert capsys.readouterr() == ("", "")
    monkeypatch.delenv("LOCAL_RANK")
    monkeypatch.chdir(sweep)  # run from elsewhere: the absolute directory, quoted for a shell where needed
    spaced = tmp_path / "my sweeps"
    spaced.mkdir()
    callback.on_multirun_end(config(directory=str(spaced)))
    assert capsys.readouterr().out == f"Table of this sweep: python -m src.tables '{spaced}'\n"


def test_the_callback_is_registered_for_every_entry_point():
    """conf/hydra/default.yaml (used by src.train, src.eval and src.predict) names the callback; it prints only
    after a sweep of src.train (test above)."""
    config = yaml.safe_load((Path(__file__).resolve().parents[1] / "conf" / "hydra" / "default.yaml").read_text())
    targets = [c["_target_"] for c in config["callbacks"].values()]
    assert "image2sphere.training.hydra_callbacks.PrintSweepTableCommand" in targets
