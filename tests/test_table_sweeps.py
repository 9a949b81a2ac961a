"""The paper's tables as sweeps (``python -m src.train table=tableN``, ``hydra/sweeper=table``): the
sweeper's union of grids, that each table file names exactly the runs its table needs, and (slow)
that every table file launches on the fixtures of the published datasets and can be tabulated."""

from __future__ import annotations

import copy
import functools
import json
import sys
from collections.abc import Sequence
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import OmegaConf

from conftest import REPO, run_module
from hydra_plugins.image2sphere_sweeper.table_sweeper import expand_grids
from image2sphere.reporting import Run, build_table, load_layouts
from test_methods_entry import METHOD_SMOKE

LAYOUTS = load_layouts()
TABLES = sorted(p.stem for p in (REPO / "conf" / "table").glob("*.yaml"))
PARSER = OverridesParser.create()
# the methods' smoke settings without lmax=2: a key on the command line replaces the table's own sweep
# of it (Table 7 would collapse to one job)
SMOKE = [a for a in METHOD_SMOKE if not a.startswith("lmax=")]


def test_union_of_grids_in_order_without_duplicates():
    jobs = expand_grids(PARSER, {"experiment": "e"}, [{"model": "a", "seed": "0,1"}, {"model": "a,b"}])
    assert jobs == [
        ["experiment=e", "model=a", "seed=0"],
        ["experiment=e", "model=a", "seed=1"],
        ["experiment=e", "model=a"],
        ["experiment=e", "model=b"],
    ]
    # "model=a" without a seed is a different job from "model=a seed=0": kept; an exact repeat is not
    assert len(expand_grids(PARSER, {}, [{"model": "a,b"}, {"model": "b,c"}])) == 3


def test_command_line_wins_over_the_grid_and_a_command_line_sweep_multiplies():
    jobs = expand_grids(PARSER, {"x": 1}, [{"lmax": "2,4"}, {"model": "m"}], ["lmax=8", "seed=0,1"])
    assert jobs == [
        ["x=1", "lmax=8", "seed=0"],
        ["x=1", "lmax=8", "seed=1"],
        ["x=1", "model=m", "lmax=8", "seed=0"],
        ["x=1", "model=m", "lmax=8", "seed=1"],
    ]
    assert expand_grids(PARSER, {}, [{"flag": True, "none": None}]) == [
        ["flag=True", "none=null"]
    ]  # booleans as Hydra writes them


# The tables' jobs are composed by several tests here and in test_documented_commands (a sweep directory
# for each table command): each table's grid and each job's config are composed once per test process
# (the configs do not change during a session) and handed out as copies.
def table_jobs(table: str, arguments: Sequence[str] = ()) -> list[list[str]]:
    """The jobs of ``table=<table>`` by job number; ``arguments``: the command line's other (non-hydra)
    overrides, which the sweeper appends to every job."""
    params, grids = _table_grids(table)
    return expand_grids(PARSER, copy.deepcopy(params), copy.deepcopy(grids), list(arguments))


@functools.cache
def _table_grids(table: str) -> tuple[dict, list]:
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=[f"table={table}"], return_hydra_config=True)
    sweeper = cfg.hydra.sweeper
    assert sweeper._target_.endswith("TableSweeper") and cfg.hydra.mode.name == "MULTIRUN"
    return OmegaConf.to_container(sweeper.params), OmegaConf.to_container(sweeper.grids)


def composed_run(table: str, job: list[str], index: int) -> Run:
    """What the job's run directory will say it was (its group choices and config), as src.tables reads it."""
    choices, config = _composed_job(table, tuple(job))
    return Run(path=Path(f"{table}/{index}"), metrics={"acc15": 0.5}, choices=copy.deepcopy(choices),
               config=copy.deepcopy(config), overrides=list(job))  # fmt: skip


@functools.cache
def _composed_job(table: str, job: tuple[str, ...]) -> tuple[dict, dict]:
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=[f"table={table}", *job], return_hydra_config=True)
    choices = OmegaConf.to_container(cfg.hydra.runtime.choices)
    config = OmegaConf.to_container(cfg, resolve=False)
    config.pop("hydra")
    assert config["task_name"] == table.replace("/", "_")  # small/table7 runs as small_table7
    return choices, config


@pytest.mark.parametrize("table", TABLES)
def test_each_table_file_names_exactly_the_runs_of_its_table(table):
    """Every job composes; every cell of the table's layout has a job, every job fills a cell."""
    jobs = table_jobs(table)
    runs = [composed_run(table, job, i) for i, job in enumerate(jobs)]
    filled = build_table(table, LAYOUTS[table], runs)
    assert not filled.unmatched, [r.overrides for r in filled.unmatched]
    layout = LAYOUTS[table]
    for row, cells in zip(layout["rows"], filled.cells, strict=True):
        for column, cell in zip(layout["columns"], cells, strict=True):
            assert cell.runs, (table, row["label"], column["id"])
    # I2S's seeds as the paper reports them
    i2s = next(
        i for i, r in enumerate(layout["rows"]) if {**layout.get("match", {}), **r["match"]}.get("model") == "i2s"
    )
    expected_seeds = {"table1": 5, "table2": 6, "table5": 6}.get(table, 1)
    assert len(filled.cells[i2s][0].runs) == expected_seeds
    assert sorted(r.seed for r in filled.cells[i2s][0].runs) == list(range(expected_seeds))
    assert len(jobs) == {"table1": 14, "table2": 16, "table3": 36, "table4": 6, "table5": 15, "table6": 4,
                         "table7": 5, "table8": 6}[table]  # fmt: skip


def test_table5_can_be_printed_from_table1s_runs():
    runs = [composed_run("table1", job, i) for i, job in enumerate(table_jobs("table1"))]
    filled = build_table("table5", LAYOUTS["table5"], runs)
    assert not filled.unmatched and all(row[0].runs for row in filled.cells)


@pytest.mark.slow
@pytest.mark.parametrize("table", TABLES)
def test_every_table_launches_on_the_fixtures_and_is_tabulated(table, published_fixtures, tmp_path):
    """The first and the last job of each table (``hydra.sweeper.jobs``), one batch each, on the
    fixtures of the published datasets; their directories keep the job numbers of the full table;
    src.tables then fills exactly those cells."""
    jobs = table_jobs(table)
    last = len(jobs) - 1
    cmd = [sys.executable, "-m", "src.train", f"table={table}", f"hydra.sweeper.jobs=[0,{last}]",
           f"paths.data_dir={published_fixtures}", f"paths.log_dir={tmp_path}", *SMOKE]  # fmt: skip
    run_module(cmd)
    (sweep,) = (tmp_path / table / "multiruns").iterdir()
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == sorted({"0", str(last)})
    for job in (0, last):
        overrides = (sweep / str(job) / ".hydra" / "overrides.yaml").read_text()
        assert all(o in overrides for o in jobs[job]), (jobs[job], overrides)
        assert json.loads((sweep / str(job) / "metrics.json").read_text())["n_images"] > 0
    proc = run_module([sys.executable, "-m", "src.tables", str(sweep)])
    assert "not in this table" not in proc.stdout and "not finished" not in proc.stdout
    # fast_dev_run jobs (SMOKE): listed, not counted, unless --include-unfinished counts them, marked
    assert proc.stdout.count("- not counted: `") == 2 and "ours (" not in proc.stdout
    proc = run_module([sys.executable, "-m", "src.tables", str(sweep), "--include-unfinished", "--force"])
    assert proc.stdout.count("ours (1 run, 1 unfinished)") == 2  # the rows of the two jobs
    assert (sweep / "tables" / f"{table}.md").is_file() and (sweep / "tables" / f"{table}.tex").is_file()


def test_job_numbers_that_do_not_exist_are_refused_before_anything_runs(tmp_path):
    cmd = [sys.executable, "-m", "src.train", "table=table6", "hydra.sweeper.jobs=[1,9]", f"paths.log_dir={tmp_path}"]
    proc = run_module(cmd, check=False)
    assert proc.returncode != 0
    assert "hydra.sweeper.jobs: job numbers [9] do not exist; this sweep has jobs 0..3" in proc.stderr
    assert not list(tmp_path.rglob("metrics.json")) and not list(tmp_path.rglob("*.ckpt"))


# ------------------------------------------------------------------ the small-scale sweeps (conf/table/small/)
def _flat(cfg: dict, prefix: str = "") -> dict[str, object]:
    out = {}
    for key, value in cfg.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def test_small_sweeps_train_every_setting_on_the_built_in_data_with_one_change_each():
    """table=small/table7 and small/ablations: on the built-in data, 2 epochs, level-4 test grid, each
    setting over seeds 0, 1 and 2; Table 7's band limits, and every other setting one change from the
    default of the same seed (the lmax 6 run of small/table7)."""
    seeds = (0, 1, 2)
    bases, default = {}, None
    for seed in seeds:
        default = composed_run("small/table7", [f"seed={seed}", "lmax=6"], 0)
        bases[seed] = _flat(default.config)
        assert default.choices["dataset"] == "symsol_rendered" and default.choices["model"] == "i2s"
        assert (bases[seed]["trainer.max_epochs"], bases[seed]["eval_grid_level"], bases[seed]["lmax"]) == (2, 4, 6)
        assert bases[seed]["seed"] == seed
    assert table_jobs("small/table7") == [[f"seed={s}", f"lmax={L}"] for s in seeds for L in (2, 4, 6, 8, 10)]
    changed: dict[str, list] = {}
    for i, job in enumerate(table_jobs("small/ablations")):
        run = composed_run("small/ablations", job, i)
        assert run.choices["dataset"] == "symsol_rendered", job
        flat = _flat(run.config)
        base = bases[flat["seed"]]
        assert (flat["trainer.max_epochs"], flat["eval_grid_level"]) == (2, 4), job
        differs = {k for k in set(base) | set(flat) if k not in ("task_name", "tags") and base.get(k) != flat.get(k)}
        groups = {g for g in ("model", "encoder") if run.choices[g] != default.choices[g]}
        setting = " ".join(o for o in job if not o.startswith("seed="))
        changed.setdefault(setting, []).append((flat["seed"], groups, differs))
    assert all(sorted(s for s, _, _ in runs) == list(seeds) for runs in changed.values()), changed
    changed = {k: {(frozenset(g), frozenset(d)) for _, g, d in runs} for k, runs in changed.items()}
    for runs in changed.values():
        assert len(runs) == 1, runs  # the same change at every seed
    changed = {k: next(iter(runs)) for k, runs in changed.items()}
    # a mapping or a number of SO(3) convolutions: another model file, nothing else
    for model in ("i2s_spatial_filter", "i2s_harmonic_projector_spatial_filter", "i2s_harmonic_projector",
                  "fourier_mlp", "i2s_icosahedral", "i2s_no_so3_conv", "i2s_two_so3_conv"):  # fmt: skip
        groups, differs = changed.pop(f"model={model}")
        assert groups == {"model"} and all(k.startswith("model.") for k in differs), (model, differs)
    groups, differs = changed.pop("encoder=resnet50")
    assert groups == {"encoder"} and differs == {"encoder.depth"}, differs
    for level in (2, 4):
        groups, differs = changed.pop(f"train_grid_level={level}")
        assert not groups and differs == {"train_grid_level"}, differs
    assert changed.pop("model.net.n_subset=20 lmax=8") == (set(), {"model.net.n_subset", "lmax"})
    assert not changed, changed


def test_small_successors_trains_four_methods_at_one_budget_on_three_sets_and_three_seeds():
    """table=small/successors: I2S, the two methods after it and IPDF, each on the default cube + cone, the
    tetrahedron alone and tetX alone, seeds 0-2 (seed by seed), every job with the same budget (encoder,
    optimiser, schedule, 2 epochs, level-3 test grid); the jobs of one data set differ only in the model,
    and the Wigner-D regression adds the distribution loss, as its authors train it on SYMSOL."""
    jobs = table_jobs("small/successors")
    runs = [composed_run("small/successors", job, i) for i, job in enumerate(jobs)]
    sets = {"cube-cone": (["cube", "cone"], None), "tet": (["tet"], None), "tetX": (None, "tetX")}
    seen = {}
    budget = set()
    for run in runs:
        flat = _flat(run.config)
        assert run.choices["dataset"] == "symsol_rendered"
        name = next(n for n, pair in sets.items() if pair == (flat["dataset.shapes"], flat["dataset.shape"]))
        seen.setdefault((name, flat["seed"]), set()).add(run.choices["model"])
        if run.choices["model"] == "wigner_regression":  # with the distribution loss, as on SYMSOL
            assert flat["model.net.distribution_weight"] == 1.0
        groups = tuple(run.choices[g] for g in ("encoder", "optimizer", "scheduler"))
        keys = ("trainer.max_epochs", "eval_grid_level", "model.spread_grid_level", "dataset.batch_size")
        budget.add((*groups, *(flat[k] for k in keys)))
    methods = {"i2s", "wigner_regression", "rotation_flow", "ipdf"}
    assert seen == {(n, s): methods for n in sets for s in (0, 1, 2)}
    assert budget == {("resnet18", "adam", "step", 2, 3, 3, 32)}
    assert [_flat(r.config)["seed"] for r in runs] == [s for s in (0, 1, 2) for _ in range(12)]  # seed by seed
    order = ["i2s", "wigner_regression", "rotation_flow", "ipdf"]
    assert [r.choices["model"] for r in runs] == order * 9  # job 4k + i is method i


def test_small_symsol_trains_symsol_one_once_and_each_symsol_two_shape_alone(tmp_path):
    """table=small/symsol: on the renderer, 8 epochs (x0.1 after 6), level-4 test grid; SYMSOL I's five
    shapes in one model and each SYMSOL II shape in its own, each with one random label and with every
    equivalent label, over seeds 0, 1 and 2; and the datamodule each job builds trains on those shapes."""
    from image2sphere.data.datamodule import SymsolDataModule

    jobs = table_jobs("small/symsol")
    assert len(jobs) == 3 * 2 * (1 + 3)
    seen = set()
    for i, job in enumerate(jobs):
        run = composed_run("small/symsol", job, i)
        flat = _flat(run.config)
        assert run.choices["dataset"] == "symsol_rendered" and run.choices["model"] == "i2s", job
        assert (flat["trainer.max_epochs"], flat["model.scheduler.step_size"], flat["eval_grid_level"]) == (8, 6, 4)
        shapes, shape = run.config["dataset"]["shapes"], flat["dataset.shape"]
        assert (shapes is None) != (shape is None), job  # SymsolDataModule takes one of the two
        dm = SymsolDataModule(
            root=None, render={"train": 1, "test": 1}, render_dir=str(tmp_path), shapes=shapes, shape=shape,
            label=flat["dataset.label"],
        )  # fmt: skip
        seen.add((flat["seed"], flat["dataset.label"], dm.shapes))
    shapes = [("tet", "cube", "icosa", "cone", "cyl"), ("tetX",), ("cylO",), ("sphereX",)]
    assert seen == {(s, label, sh) for s in (0, 1, 2) for label in ("random", "all") for sh in shapes}
