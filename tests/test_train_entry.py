"""``python -m src.train`` end to end: fast_dev_run, a two-job sweep, exact resume, faults.

Each run renders (once, cached in a per-session directory) a tiny SYMSOL-style set and trains a
small I2S on it; everything is written under pytest's tmp directories.
"""

from __future__ import annotations

import math
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from conftest import ENV, REPO, SMOKE, read_metrics, run_module, run_train, train_command
from image2sphere.testing.commands import process_group


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("data")


def test_fast_dev_run_through_entry_point(tmp_path, data_dir):
    proc = run_train(["debug=fdr", f"hydra.run.dir={tmp_path / 'run'}"], data_dir, tmp_path / "logs")
    # the start-up log says what the run trains and which protocol the dataset brought
    log = proc.stdout + proc.stderr
    assert "This run trains (dataset=symsol_rendered brings protocol=symsol_rendered" in log
    assert "optimizer  adam: Adam(lr=0.001, weight_decay=0.0, fused=True)  [protocol=symsol_rendered]" in log
    metrics = read_metrics(tmp_path / "run")
    assert {"log_likelihood/cube", "log_likelihood/cone", "spread_deg", "acc15", "median_error_deg"} <= set(metrics)
    assert metrics["n_images"] > 0
    assert (tmp_path / "run" / ".hydra" / "config.yaml").is_file()
    # the rendered set is in the published layout, cached for later runs
    (rendered,) = (data_dir / "symsol_rendered").iterdir()
    assert (rendered / "train" / "rotations.npz").is_file() and (rendered / "test" / "images").is_dir()


def test_default_run_dirs_are_unique_and_existing_dirs_are_refused(tmp_path, data_dir):
    logs = tmp_path / "logs"
    run_train(["debug=fdr"], data_dir, logs)
    run_train(["debug=fdr"], data_dir, logs)
    runs = sorted((logs / "debug" / "runs").iterdir())
    assert len(runs) == 2 and all((r / "metrics.json").is_file() for r in runs)
    before = {p: p.stat().st_mtime_ns for p in runs[0].rglob("*")}
    proc = run_train(["debug=fdr", f"hydra.run.dir={runs[0]}"], data_dir, logs, check=False)
    assert proc.returncode != 0 and "already holds files" in proc.stderr
    assert {p: p.stat().st_mtime_ns for p in runs[0].rglob("*")} == before  # untouched


def test_missing_checkpoint_is_reported(tmp_path, data_dir):
    proc = run_train(["debug=fdr", "ckpt_path=/nonexistent/last.ckpt"], data_dir, tmp_path / "logs", check=False)
    assert proc.returncode != 0 and "ckpt_path=/nonexistent/last.ckpt does not exist" in proc.stderr


def test_nan_loss_stops_without_writing_a_checkpoint(tmp_path, data_dir):
    run = tmp_path / "run"
    args = ["logger=none", "trainer.max_epochs=3", "model.optimizer.lr=1e30", f"hydra.run.dir={run}"]
    proc = run_train(args, data_dir, tmp_path / "logs", check=False)
    assert proc.returncode != 0
    assert "NonFiniteLossError" in proc.stderr and "Lower model.optimizer.lr" in proc.stderr
    # the first step diverged: there is nothing to resume from, and the message says so
    assert "no checkpoint was written yet" in proc.stderr and not (run / "checkpoints" / "last.ckpt").exists()
    assert not (run / "metrics.json").exists()
    for ckpt in (run / "checkpoints").glob("*.ckpt"):  # whatever was saved holds finite weights only
        state = torch.load(ckpt, map_location="cpu", weights_only=False)["state_dict"]
        assert all(torch.isfinite(v).all() for v in state.values() if v.is_floating_point())


@pytest.mark.slow
def test_multirun_sweep_runs_each_job_in_its_own_directory(tmp_path, data_dir):
    logs = tmp_path / "logs"
    run_train(["-m", "lmax=2,3", "logger=csv", "trainer.max_epochs=1"], data_dir, logs)
    (sweep,) = (logs / "train" / "multiruns").iterdir()
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir() and p.name.isdigit())
    assert [j.name for j in jobs] == ["0", "1"]
    for job, lmax in zip(jobs, (2, 3), strict=True):
        assert f"lmax: {lmax}" in (job / ".hydra" / "config.yaml").read_text()
        assert (job / "checkpoints" / "last.ckpt").is_file() and (job / "metrics.json").is_file()
        assert (job / "csv").is_dir()


@pytest.mark.slow
def test_resume_from_last_checkpoint_matches_uninterrupted_run(tmp_path, data_dir):
    logs = tmp_path / "logs"
    common = ["logger=csv", "model.scheduler.step_size=1", "model.optimizer.lr=0.01"]
    full, first, resumed = tmp_path / "full", tmp_path / "first", tmp_path / "resumed"
    run_train([*common, "trainer.max_epochs=3", f"hydra.run.dir={full}"], data_dir, logs)
    run_train([*common, "trainer.max_epochs=2", f"hydra.run.dir={first}"], data_dir, logs)
    first_files = {p: p.stat().st_mtime_ns for p in first.rglob("*")}
    ckpt = first / "checkpoints" / "last.ckpt"
    run_train([*common, "trainer.max_epochs=3", f"ckpt_path={ckpt}", f"hydra.run.dir={resumed}"], data_dir, logs)

    a = torch.load(full / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    b = torch.load(resumed / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert a["epoch"] == b["epoch"] and a["global_step"] == b["global_step"]
    assert a["lr_schedulers"][0]["last_epoch"] == b["lr_schedulers"][0]["last_epoch"] == 3
    for key, value in a["state_dict"].items():
        torch.testing.assert_close(b["state_dict"][key], value, rtol=1e-5, atol=1e-6, msg=f"weights differ: {key}")
    for key, state in a["optimizer_states"][0]["state"].items():  # e.g. Adam's moments and step counts
        for name, value in state.items():
            torch.testing.assert_close(b["optimizer_states"][0]["state"][key][name], value, rtol=1e-5, atol=1e-6)
    ma, mb = read_metrics(full), read_metrics(resumed)
    for key, value in ma.items():
        if not key.endswith("_seconds"):
            assert mb[key] == pytest.approx(value, rel=1e-4, abs=1e-4), key
    assert {p: p.stat().st_mtime_ns for p in first.rglob("*")} == first_files  # the old run is untouched


@pytest.mark.slow
def test_run_killed_mid_epoch_resumes_from_its_last_epoch(tmp_path, data_dir):
    logs, killed = tmp_path / "logs", tmp_path / "killed"
    cmd = train_command(["logger=none", "trainer.max_epochs=100", f"hydra.run.dir={killed}"], data_dir, logs)
    ckpt = killed / "checkpoints" / "last.ckpt"
    with process_group(cmd, cwd=REPO, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) as proc:
        deadline = time.monotonic() + 600
        while not ckpt.exists() and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.2)
        assert ckpt.exists(), "no checkpoint was written"
        time.sleep(1.0)  # into the next epoch; leaving the block kills the run (SIGKILL: no chance to clean up)
    saved = torch.load(ckpt, map_location="cpu", weights_only=True)  # complete, loadable, plain types only
    steps_per_epoch = 3  # 2 shapes x (10 - 2 validation) images in batches of 6
    assert saved["global_step"] % steps_per_epoch == 0 and saved["global_step"] >= steps_per_epoch
    epochs_done = saved["global_step"] // steps_per_epoch
    resumed = tmp_path / "resumed"
    proc = run_train(
        ["logger=csv", f"trainer.max_epochs={epochs_done + 1}", f"ckpt_path={ckpt}", f"hydra.run.dir={resumed}"],
        data_dir,
        logs,
    )
    assert "Restored all states from the checkpoint" in proc.stdout + proc.stderr
    final = torch.load(resumed / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert final["global_step"] == saved["global_step"] + steps_per_epoch  # only the lost epoch was redone


# ------------------------------------------------------------------ the paper's experiments on fixtures

EXPERIMENTS = sorted(p.stem for p in (REPO / "conf" / "experiment").glob("*.yaml"))


def _run_experiment(experiment: str, data_dir: Path, log_dir: Path) -> dict:
    cmd = [sys.executable, "-m", "src.train", f"experiment={experiment}", *SMOKE,
           f"paths.data_dir={data_dir}", f"paths.log_dir={log_dir}"]  # fmt: skip
    run_module(cmd)
    (run_dir,) = (log_dir / experiment / "runs").iterdir()
    return read_metrics(run_dir)


def test_pascal3d_experiment_runs_on_published_layout_fixtures(tmp_path, published_fixtures):
    metrics = _run_experiment("pascal3d", published_fixtures, tmp_path / "logs")
    assert metrics["n_images"] == 4  # fast_dev_run: one test batch
    assert 0 <= metrics["median_error_deg"] <= 180 and math.isfinite(metrics["log_likelihood"])
    assert "skipped_images" not in metrics


@pytest.mark.slow
@pytest.mark.parametrize("experiment", [e for e in EXPERIMENTS if e != "pascal3d"])
def test_every_experiment_runs_on_published_layout_fixtures(tmp_path, published_fixtures, experiment):
    metrics = _run_experiment(experiment, published_fixtures, tmp_path / "logs")
    assert 0 < metrics["n_images"] <= 4  # fast_dev_run: one test batch (a SYMSOL II fixture has 3 test images)
    assert 0 <= metrics["median_error_deg"] <= 180 and math.isfinite(metrics["log_likelihood"])
