"""Every baseline method end to end: ``python -m src.train -m model=...`` on the fixtures of each
published dataset, and ``src.eval`` / ``src.predict`` / :class:`Predictor` on a checkpoint of each.

The methods share one interface (``output_distribution`` -> a ``PoseDistribution``, ``loss``); these
tests check that each family's metrics carry the keys it has (a point regressor: no log likelihood
or spread, ``n/a`` in the tables; a family with a closed-form normaliser: ``log_likelihood_exact``)
through every entry point. All models of a sweep run in one Hydra multirun (one start-up).
"""

from __future__ import annotations

import itertools
import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from PIL import Image

from conftest import ENV as TRAIN_ENV
from conftest import REPO, SMOKE, TINY, haar_rotations, run_module
from image2sphere.distributions.base import PointEstimate, PoseDistribution
from image2sphere.inference import Predictor
from image2sphere.metrics import HDR_COVERAGE_KEYS

# model config -> (has a density, has a closed-form normaliser, i.e. reports log_likelihood_exact)
FAMILIES = {
    "regression_6d": (False, False),
    "regression_9d": (False, False),
    "spherical_regression": (False, False),
    "bin_delta": (False, False),
    "i2s_icosahedral": (False, False),
    "viewpoint_bins": (True, True),
    "matrix_fisher": (True, True),
    "rotation_laplace": (True, True),
    "bingham": (True, True),
    "von_mises": (True, True),
    "ipdf": (True, False),
    "fourier_mlp": (True, False),
    "wigner_regression": (True, False),
    "rotation_flow": (True, True),
}
MODELS = list(FAMILIES)
REGRESSORS = [m for m, (density, _) in FAMILIES.items() if not density]

# the caller's thread count wins (the suite may share the machine with other work)
ENV = {**TRAIN_ENV, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", TRAIN_ENV["OMP_NUM_THREADS"])}

# SMOKE (fast_dev_run, batch 4, level-3 metrics, no logger) made smaller still: 32 px, ResNet-18, lmax 2
METHOD_SMOKE = [*SMOKE, "dataset.image_size=32", "encoder=resnet18", "lmax=2", "trainer.accelerator=cpu",
                "callbacks.progress_bar.refresh_rate=0"]  # fmt: skip
# the headline numbers every method reports, and those only a density has
HEADLINE = ("acc15", "acc30", "median_error_deg")
DENSITY_ONLY = ("log_likelihood", "spread_deg", "calibration_ece", *HDR_COVERAGE_KEYS)
TABLE_HEADER = ["class", "log lik.", "spread", "ECE", "acc@15", "acc@30", "med.err"]
N_DENSITY_COLUMNS = 3  # log lik., spread, ECE: n/a for a point regressor
RECALIBRATED_HEADER = ["LL recal.", "ECE recal."]


def test_every_model_config_is_covered_here():
    """A new method (conf/model/<name>.yaml) must be added to FAMILIES; I2S and its ablations are tested
    elsewhere (the icosahedral group version, a point estimate, is here)."""
    configs = {p.stem for p in (REPO / "conf" / "model").glob("*.yaml")}
    assert set(MODELS) <= configs
    i2s_variants = {c for c in configs if c == "i2s" or c.startswith("i2s_")} - {"i2s_icosahedral"}
    assert sorted(configs - set(MODELS)) == sorted(i2s_variants)


def _run(args: list[str], timeout: int = 900) -> subprocess.CompletedProcess:
    return run_module([sys.executable, "-m", *args], env=ENV, timeout=timeout)


def _sweep_jobs(sweep: Path) -> dict[str, Path]:
    """model name -> job directory of a multirun over ``model=``."""
    jobs = {}
    for job in sorted(p for p in sweep.iterdir() if p.is_dir() and p.name.isdigit()):
        overrides = (job / ".hydra" / "overrides.yaml").read_text()
        (model,) = re.findall(r"^- model=(\w+)$", overrides, re.M)
        jobs[model] = job
    return jobs


def printed_tables(stdout: str) -> dict[str, list[list[str]]]:
    """The metrics tables a run printed, by the run directory printed under each: rows of cells (the
    first row the header's titles)."""
    tables = {}
    for body, run_dir in re.findall(r"Test metrics \([^\n]*\):\n(.*?)\nRun directory: (\S+)", stdout, re.S):
        header, *rows = body.splitlines()
        titles = re.split(r"\s{2,}", header.strip())
        tables[str(Path(run_dir).resolve())] = [titles, *[row.split() for row in rows]]
    return tables


def markdown_table(text: str) -> dict[str, list[str]]:
    """The columns of the first markdown table in ``text``: title -> cells (the class column under "class")."""
    block = itertools.takewhile(
        lambda line: line.startswith("|"), itertools.dropwhile(lambda line: not line.startswith("|"), text.splitlines())
    )
    lines = [line for line in block if not line.startswith("|---")]  # the first table: the metrics
    header, *rows = [[cell.strip() for cell in line.strip("|").split("|")] for line in lines]
    return {title: [row[i] for row in rows] for i, title in enumerate(header)}


def _is_float(cell: str) -> bool:
    try:
        return math.isfinite(float(cell))
    except ValueError:
        return False


def check_metrics(model: str, metrics: dict) -> None:
    density, closed_form = FAMILIES[model]
    assert metrics["n_images"] > 0, model
    for key in HEADLINE:
        assert math.isfinite(metrics[key]), (model, key, metrics[key])
    assert 0 <= metrics["acc15"] <= metrics["acc30"] <= 1 and 0 <= metrics["median_error_deg"] <= 180, model
    if density:
        for key in DENSITY_ONLY:
            assert math.isfinite(metrics[key]), (model, key, metrics.get(key))
        assert 0 <= metrics["spread_deg"] <= 180, model
        # calibration: per class and the class mean, coverage growing with the HDR's mass
        for name in [""] + sorted({k.split("/")[1] for k in metrics if k.startswith("calibration_ece/")}):
            key = f"/{name}" if name else ""
            coverage = [metrics[c + key] for c in HDR_COVERAGE_KEYS]
            assert all(0 <= c <= 1 for c in coverage) and coverage == sorted(coverage), (model, key, coverage)
            assert 0 <= metrics["calibration_ece" + key] <= 0.9, (model, key)
        assert any(k.startswith("calibration_ece/") for k in metrics), model
    else:  # neither the headline nor any per-class value
        absent = [k for k in metrics if k.split("/")[0] in DENSITY_ONLY or k.startswith(("log_likelihood", "hdr_"))]
        assert absent == [], f"{model} is a point regressor but reports {absent}"
    if closed_form:
        assert math.isfinite(metrics["log_likelihood_exact"]), model
    else:
        assert not [k for k in metrics if k.startswith("log_likelihood_exact")], model


def check_printed_table(model: str, table: list[list[str]], metrics: dict) -> None:
    """Every column is printed; a regressor's log likelihood, spread and ECE read n/a in every row; a run
    with a recalibration (``temperature`` in its metrics: a density method with a validation split) also
    has the log likelihood and ECE after it, and a family with a closed-form density its exact log likelihood."""
    density, _ = FAMILIES[model]
    header, *rows = table
    recalibrated = "temperature" in metrics
    assert not recalibrated or density, model  # a point regressor has nothing to recalibrate
    own = ["LL exact"] if "log_likelihood_exact" in metrics else []  # a closed-form family's own metric
    assert header == TABLE_HEADER + (RECALIBRATED_HEADER if recalibrated else []) + own, (model, header)
    assert rows and rows[-1][0] == "mean", (model, rows)
    last = 1 + N_DENSITY_COLUMNS
    for row in rows:
        assert len(row) == len(header), (model, row)
        assert all(_is_float(cell) for cell in row[last:]), (model, row)
        if density:
            assert all(_is_float(cell) for cell in row[1:last]), (model, row)
        else:
            assert row[1:last] == ["n/a"] * N_DENSITY_COLUMNS, (model, row)


# ------------------------------------------------------------------ all methods on each dataset's fixtures
def _run_methods(dataset: str, data_dir: Path, tmp_path: Path) -> None:
    sweep = tmp_path / "sweep"
    paths = [f"paths.data_dir={data_dir}", f"paths.log_dir={tmp_path / 'logs'}", f"hydra.sweep.dir={sweep}"]
    proc = _run(["src.train", "-m", f"model={','.join(MODELS)}", f"dataset={dataset}", *METHOD_SMOKE, *paths])
    jobs = _sweep_jobs(sweep)
    assert sorted(jobs) == sorted(MODELS)
    tables = printed_tables(proc.stdout)
    for model, job in jobs.items():
        assert "image_size: 32" in (job / ".hydra" / "config.yaml").read_text(), model
        metrics = json.loads((job / "metrics.json").read_text())
        assert 0 < metrics["n_images"] <= 4, (model, metrics["n_images"])  # fast_dev_run: one test batch
        check_metrics(model, metrics)
        check_printed_table(model, tables[str(job.resolve())], metrics)


def test_every_method_runs_on_symsol1_fixtures(tmp_path, published_fixtures):
    _run_methods("symsol1", published_fixtures, tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("dataset", ["symsol2", "modelnet10", "pascal3d"])
def test_every_method_runs_on_published_layout_fixtures(tmp_path, published_fixtures, dataset):
    _run_methods(dataset, published_fixtures, tmp_path)


# ------------------------------------------------------------------ a checkpoint of each family
@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory) -> dict[str, Path]:
    """model name -> ``last.ckpt`` of one epoch (one training batch) on the tiny built-in data."""
    root = tmp_path_factory.mktemp("methods")
    tiny = [a for a in TINY if not a.startswith("model.net.")]  # I2S's network settings
    sweep = root / "sweep"
    _run(["src.train", "-m", f"model={','.join(MODELS)}", *tiny, "trainer.max_epochs=1",
          "trainer.limit_train_batches=1", "trainer.limit_val_batches=1", "logger=none",
          f"paths.data_dir={root / 'data'}", f"paths.log_dir={root / 'logs'}", f"hydra.sweep.dir={sweep}"])  # fmt: skip
    jobs = _sweep_jobs(sweep)
    assert sorted(jobs) == sorted(MODELS)
    return {model: job / "checkpoints" / "last.ckpt" for model, job in jobs.items()}


@pytest.mark.slow
@pytest.mark.parametrize("model", MODELS)
def test_eval_predict_and_predictor_on_each_family(checkpoints, tmp_path, model):
    from image2sphere.data.raycast import render

    density, closed_form = FAMILIES[model]
    ckpt = checkpoints[model]
    assert ckpt.is_file()

    out = tmp_path / "eval"
    proc = _run(
        ["src.eval", f"ckpt_path={ckpt}", "eval_grid_level=3", "plots=1", "logger=none", f"hydra.run.dir={out}"]
    )
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["n_images"] == 6 and metrics["eval_grid_level"] == 3  # every test image: 2 shapes x 3
    check_metrics(model, metrics)
    check_printed_table(model, printed_tables(proc.stdout)[str(out.resolve())], metrics)
    columns = markdown_table((out / "metrics.md").read_text())
    assert columns["class"] == ["cube", "cone", "mean"]
    assert all(_is_float(c) for c in columns["med.err"] + columns["acc@15"]), columns
    for title in ("log lik.", "spread", "ECE"):  # a density's numbers; a regressor's column reads n/a, as printed
        cells = columns.get(title)
        if density:
            assert cells and all(_is_float(c) for c in cells), columns
        else:
            assert cells is not None and set(cells) == {"n/a"}, columns
    assert (out / "plots" / "test_0.png").read_bytes()[:4] == b"\x89PNG"
    # the reliability diagram of a density's calibration; a regressor has none
    reliability = out / "reliability.png"
    assert (reliability.read_bytes()[:4] == b"\x89PNG") if density else not reliability.exists(), model

    image = tmp_path / "cube.png"
    Image.fromarray(render("cube", haar_rotations(1, seed=4, dtype=torch.float32), 64)[0].numpy()).save(image)
    proc = _run(
        ["src.predict", f"ckpt_path={ckpt}", f"image={image}", "eval_grid_level=3", f"hydra.run.dir={tmp_path / 'run'}"]
    )
    assert "mode 1: mass" in proc.stdout and "YXY angles" in proc.stdout, proc.stdout
    assert (tmp_path / "cube_so3.png").read_bytes()[:4] == b"\x89PNG"

    dist = Predictor.from_checkpoint(ckpt)(image)  # recalibrated by the run's temperature, if it has one
    raw = Predictor.from_checkpoint(ckpt, recalibration=False)(image)
    assert isinstance(dist, PoseDistribution) and dist.batch_size == 1
    assert dist.has_density is density and raw.has_exact_density is closed_form
    if density and "temperature" in metrics:  # the network's distribution tempered by the stored temperature
        expected = torch.log_softmax(raw.grid_log_density(2).double() / metrics["temperature"], dim=1)
        torch.testing.assert_close(dist.log_prob_grid(2).double(), expected, rtol=1e-4, atol=1e-4)
    assert isinstance(dist, PointEstimate) is not density
    rotations, mass = dist.modes(level=3, k=5)[0]  # src.predict's defaults: the same modes as printed
    assert len(mass) >= 1 and rotations.shape == (len(mass), 3, 3)
    first_row = "[" + " ".join(f"{float(v): .4f}" for v in rotations[0, 0]) + "]"
    assert first_row in proc.stdout, (first_row, proc.stdout)
    if not density:  # the point estimate is the single mode, with all the mass
        assert "mode 1: mass 1.000" in proc.stdout and "mode 2" not in proc.stdout
        torch.testing.assert_close(rotations[0], dist.mode()[0])
