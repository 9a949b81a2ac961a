"""``python -m src.eval``, ``python -m src.predict``, the Predictor API and safe checkpoint loading,
on a tiny checkpoint trained inside the test."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from PIL import Image

from conftest import haar_rotations, read_metrics, run_module
from image2sphere.inference import Predictor
from image2sphere.metrics import HDR_COVERAGE_KEYS
from image2sphere.training.checkpoint import CheckpointError, build_module, load_checkpoint


@pytest.fixture
def trained(tiny_run) -> tuple[Path, Path, Path]:
    """(checkpoint, its run directory, the data directory) of the session's tiny run (conftest.tiny_run)."""
    return tiny_run / "checkpoints" / "last.ckpt", tiny_run, tiny_run.parent / "data"


def _run(module: str, args: list[str], check: bool = True) -> subprocess.CompletedProcess:
    return run_module([sys.executable, "-m", module, *args], check=check)


def test_training_plots_fixed_validation_images_into_the_run_and_the_logger(trained):
    _, run, _ = trained
    assert sorted(p.name for p in (run / "plots").iterdir()) == ["epoch=000_image=0.png", "epoch=000_image=1.png"]
    events = list((run / "tensorboard").rglob("events.out.tfevents.*"))
    assert events and max(e.stat().st_size for e in events) > 10_000  # the figures went to TensorBoard too


def test_validation_logs_each_class_curve_whose_mean_is_the_logged_mean(trained):
    """A shape that stays at uniform while the others learn shows in the logger, not only in the test."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    _, run, _ = trained
    (events,) = {e.parent for e in (run / "tensorboard").rglob("events.out.tfevents.*")}
    scalars = EventAccumulator(str(events), size_guidance={"scalars": 0}).Reload()
    tags = set(scalars.Tags()["scalars"])
    for metric in ("log_likelihood", "acc15", "median_error_deg"):
        assert {f"val/{metric}/cube", f"val/{metric}/cone"} <= tags, sorted(tags)
    mean, cube, cone = (scalars.Scalars(f"val/log_likelihood{c}")[-1].value for c in ("", "/cube", "/cone"))
    assert mean == pytest.approx((cube + cone) / 2, rel=1e-5)


def test_eval_scores_every_test_image_and_reproduces_the_training_metrics(trained, tmp_path):
    ckpt, run, _ = trained
    out = tmp_path / "eval"
    # batch 4 over 6 test images: the last batch is partial and must be scored; no eval_grid_level: the
    # level the run was tested at (3), not the paper's 5
    proc = _run("src.eval", [f"ckpt_path={ckpt}", "batch_size=4", "plots=2", f"hydra.run.dir={out}", "logger=csv"])
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["eval_grid_level"] == 3
    assert "unfinished" not in metrics and "UNFINISHED" not in proc.stdout  # the run trained its 1 epoch
    assert "Evaluating on the grid of level 3 (the level its run was tested at" in proc.stdout + proc.stderr
    assert "The test of 6 images on the grid of level 3 will take about" in proc.stdout  # 4 + 2, not 2 x 4
    trained_metrics = read_metrics(run)
    assert metrics["n_images"] == trained_metrics["n_images"] == 6
    # the calibration's tie-break is drawn per image, so the same images give the same coverage in any batch
    for key in ("log_likelihood", "log_likelihood/cube", "spread_deg", "median_error_deg/cone", "acc15",
                "calibration_ece", "calibration_ece/cone", "hdr_coverage_50/cube", *HDR_COVERAGE_KEYS):  # fmt: skip
        assert metrics[key] == pytest.approx(trained_metrics[key], rel=1e-5, abs=1e-6), key
    table = (out / "metrics.md").read_text()
    assert "| class | log lik. | spread | ECE |" in table and "| cube |" in table and "| mean |" in table
    assert (out / "reliability.png").read_bytes()[:4] == b"\x89PNG"
    assert "med.err" in proc.stdout and str(ckpt) in proc.stdout
    pngs = sorted(p.name for p in (out / "plots").iterdir())
    assert pngs == ["test_0.png", "test_1.png"]
    assert (out / "csv").is_dir()  # logged to the configured logger
    # a second evaluation into the same directory is refused, nothing overwritten
    before = (out / "metrics.json").read_bytes()
    proc = _run("src.eval", [f"ckpt_path={ckpt}", f"hydra.run.dir={out}", "eval_grid_level=3"], check=False)
    assert proc.returncode != 0 and (out / "metrics.json").read_bytes() == before


def test_eval_recomputes_batchnorm_statistics_as_training_did(trained, tmp_path):
    """``batchnorm_statistics=recompute`` recomputes the statistics from the checkpoint's weights over its
    last epoch's first batches, as ``callbacks.batchnorm_statistics`` (on in the tiny run) did at the end of
    training: the metrics are the training run's. Over one batch instead of the epoch's the statistics,
    and so the metrics, differ; the checkpoint is not changed."""
    ckpt, run, _ = trained
    before = ckpt.read_bytes()
    common = [f"ckpt_path={ckpt}", "eval_grid_level=3", "plots=0", "logger=none", "batchnorm_statistics=recompute"]
    _run("src.eval", [*common, f"hydra.run.dir={tmp_path / 'all'}"])
    _run("src.eval", [*common, "batchnorm_batches=1", f"hydra.run.dir={tmp_path / 'one'}"])
    every, one, trained_metrics = read_metrics(tmp_path / "all"), read_metrics(tmp_path / "one"), read_metrics(run)
    for key in ("log_likelihood", "spread_deg", "median_error_deg"):
        assert every[key] == pytest.approx(trained_metrics[key], rel=1e-5, abs=1e-6), key
    assert abs(one["log_likelihood"] - every["log_likelihood"]) > 1e-4
    assert ckpt.read_bytes() == before
    bad = [*common[:-1], "batchnorm_statistics=yes", f"hydra.run.dir={tmp_path / 'bad'}"]
    proc = _run("src.eval", bad, check=False)
    assert proc.returncode != 0 and "batchnorm_statistics" in proc.stderr


@pytest.mark.parametrize(("given", "run_config", "expected"), [
    (None, {"callbacks": {"batchnorm_statistics": {"num_batches": 7}}}, 7),  # the checkpoint's run's number
    (None, {"callbacks": {}}, 50),  # trained without the callback: its default
    (3, {"callbacks": {"batchnorm_statistics": {"num_batches": 7}}}, 3),  # given on the command line
])  # fmt: skip
def test_eval_recomputes_over_as_many_batches_as_the_checkpoints_run_unless_told(monkeypatch, given, run_config,
                                                                                 expected):  # fmt: skip
    """Quick. ``batchnorm_batches=null`` (the default) reads the number the checkpoint's run gave
    ``callbacks.batchnorm_statistics``."""
    import image2sphere.training.callbacks as callbacks
    from image2sphere.training.evaluate import _recompute_batchnorm_statistics

    seen = []
    monkeypatch.setattr(callbacks, "recompute_batchnorm_statistics", lambda *a, **k: seen.append(a[2]))
    datamodule = SimpleNamespace(setup=lambda stage: None, train_dataloader=lambda: None)
    trainer = SimpleNamespace(strategy=SimpleNamespace(root_device=torch.device("cpu")))
    _recompute_batchnorm_statistics(torch.nn.Linear(1, 1), datamodule, {"run_config": run_config, "epoch": 1}, given,
                                    trainer)  # fmt: skip
    assert seen == [expected]


def test_eval_with_refinement_changes_only_the_point_estimate(trained, tmp_path):
    ckpt, run, _ = trained
    out = tmp_path / "refined"
    _run("src.eval", [f"ckpt_path={ckpt}", "eval_grid_level=3", "refine=true", "plots=0", f"hydra.run.dir={out}",
                      "logger=none"])  # fmt: skip
    metrics, trained_metrics = json.loads((out / "metrics.json").read_text()), read_metrics(run)
    assert metrics["refine"] is True
    assert metrics["log_likelihood"] == pytest.approx(trained_metrics["log_likelihood"], rel=1e-5)
    assert metrics["median_error_deg"] != trained_metrics["median_error_deg"]


def test_predict_prints_modes_and_writes_the_plot_next_to_the_image(trained, tmp_path):
    from image2sphere.data.raycast import render

    ckpt, _, _ = trained
    image = tmp_path / "cube.png"
    Image.fromarray(render("cube", haar_rotations(1, seed=4, dtype=torch.float32), 64)[0].numpy()).save(image)
    proc = _run("src.predict", [f"ckpt_path={ckpt}", f"image={image}", "top_k=3", "eval_grid_level=3",
                                f"hydra.run.dir={tmp_path / 'run'}"])  # fmt: skip
    assert "mode 1: mass" in proc.stdout and "YXY angles" in proc.stdout
    plot = tmp_path / "cube_so3.png"
    assert plot.read_bytes()[:4] == b"\x89PNG"
    # the same command again predicts again; the plot is never overwritten: it gets the next free name
    first = plot.read_bytes()
    proc = _run("src.predict", [f"ckpt_path={ckpt}", f"image={image}", "top_k=3", "eval_grid_level=3",
                                f"hydra.run.dir={tmp_path / 'run2'}"])  # fmt: skip
    assert "mode 1: mass" in proc.stdout and f"plot: {tmp_path / 'cube_so3-1.png'} ({plot} exists" in proc.stdout
    assert plot.read_bytes() == first and (tmp_path / "cube_so3-1.png").read_bytes()[:4] == b"\x89PNG"
    proc = _run("src.predict", [f"ckpt_path={ckpt}", f"image={image}", "eval_grid_level=3", "top_k=1",
                                f"output={tmp_path / 'other.png'}", f"hydra.run.dir={tmp_path / 'run3'}"])  # fmt: skip
    assert (tmp_path / "other.png").is_file()
    assert re.search(rf"^{re.escape(str(image))}: 1 mode \(level 3, .* of the probability in it$", proc.stdout, re.M)


def test_predictor_on_a_batch_matches_the_trained_module(trained):
    ckpt, _, _ = trained
    predictor = Predictor.from_checkpoint(ckpt)
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (40, 50, 3), dtype=np.uint8) for _ in range(3)]
    dist = predictor(images)
    assert dist.batch_size == 3 and dist.lmax == predictor.lmax == 2 and predictor.image_size == 32
    module = build_module(load_checkpoint(ckpt), ckpt)
    x = predictor.preprocess(images)
    assert x.shape == (3, 3, 32, 32)
    with torch.no_grad():
        # the recalibrated distribution the module shows (its coefficients divided by the stored temperature)
        torch.testing.assert_close(dist.coeffs, module.calibrated_distribution(module(x)).coeffs)
        assert module.recalibration is not None and predictor.temperature == module.recalibration.temperature
        raw = Predictor.from_checkpoint(ckpt, recalibration=False)(images)
        torch.testing.assert_close(raw.coeffs, module(x))
        torch.testing.assert_close(dist.coeffs * predictor.temperature, raw.coeffs)
    modes = dist.modes(level=2, k=3)
    assert len(modes) == 3 and all(len(r) == len(m) <= 3 for r, m in modes)
    with pytest.raises(ValueError, match=r"uint8 of shape \(H, W, 3\)"):
        predictor([np.zeros((8, 8, 4), np.uint8)])


def test_corrupt_or_foreign_checkpoints_give_clear_errors(trained, tmp_path):
    ckpt, _, _ = trained
    data = ckpt.read_bytes()
    truncated = tmp_path / "truncated.ckpt"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match=r"truncated.ckpt is not a complete checkpoint .* it is truncated"):
        load_checkpoint(truncated)
    with pytest.raises(CheckpointError, match="checkpoint not found"):
        load_checkpoint(tmp_path / "nowhere.ckpt")
    foreign = tmp_path / "foreign.ckpt"
    torch.save({"weights": torch.zeros(2)}, foreign)
    with pytest.raises(CheckpointError, match="not a Lightning checkpoint"):
        load_checkpoint(foreign)
    no_config = tmp_path / "no_config.ckpt"
    torch.save({"state_dict": {}}, no_config)
    with pytest.raises(CheckpointError, match="no 'run_config'"):
        load_checkpoint(no_config)
    pickled = tmp_path / "pickled.ckpt"
    torch.save({"state_dict": {}, "run_config": {"model": {}}, "extra": Path("/")}, pickled)
    with pytest.raises(CheckpointError, match=r"objects other than tensors .*it names pathlib") as err:
        load_checkpoint(pickled)
    assert "weights_only" not in str(err.value)  # not torch's advice to load it unsafely
    # a config that describes another network than the weights
    content = load_checkpoint(ckpt)
    content["run_config"]["model"]["net"]["lmax"] = 3
    with pytest.raises(CheckpointError, match=r"does not fit the model .* of another shape"):
        build_module(content, "edited.ckpt")
    # and from the command line
    proc = _run("src.eval", [f"ckpt_path={truncated}", f"hydra.run.dir={tmp_path / 'e'}"], check=False)
    assert proc.returncode != 0 and "is not a complete checkpoint" in proc.stderr


def test_sigterm_in_the_eval_test_stops_after_that_batch_and_writes_nothing(trained, tmp_path, monkeypatch):
    """src.eval takes the same stop path as training (image2sphere.training.stop): the signal is recorded,
    the test stops after its batch, rank 0 says so and exits with 143; no metrics are written."""
    import image2sphere.training.evaluate as evaluate
    from image2sphere.testing.signal_at import SignalAt

    switch_off = evaluate.use_flag_only_signals

    def with_a_signal_in_the_test(trainer):
        switch_off(trainer)
        trainer.callbacks.append(SignalAt("test", occurrence=1))

    monkeypatch.setattr(evaluate, "use_flag_only_signals", with_a_signal_in_the_test)
    ckpt, _, _ = trained
    out = tmp_path / "eval"
    proc = _run("src.eval", [f"ckpt_path={ckpt}", f"hydra.run.dir={out}", "eval_grid_level=3", "batch_size=2",
                             "plots=0"], check=False)  # fmt: skip
    assert proc.returncode == 128 + signal.SIGTERM, proc.stderr[-3000:]
    assert "Stopped by SIGTERM in the test; nothing was written" in proc.stdout + proc.stderr
    assert not (out / "metrics.json").exists()


def _with(ckpt: dict, trainer: dict, epochs_done: int, batches: int, step: int) -> dict:
    """``ckpt`` with another trainer config and loop progress (as Lightning stores them)."""
    out = {**ckpt, "run_config": {**ckpt["run_config"], "trainer": {**ckpt["run_config"]["trainer"], **trainer}}}
    progress = {"current": {"processed": batches, "completed": batches}}
    out["loops"] = {"fit_loop": {"epoch_progress": {"current": {"processed": epochs_done}},
                                 "epoch_loop.batch_progress": {**progress, "is_last_batch": batches == 0}}}  # fmt: skip
    out["global_step"] = step
    return out


def test_an_unfinished_or_smoke_runs_checkpoint_is_named_as_such(trained):
    from image2sphere.training.evaluate import unfinished_training

    ckpt = torch.load(trained[0], map_location="cpu", weights_only=True)
    assert unfinished_training(ckpt) is None  # the tiny run: 1 epoch of max_epochs=1
    assert unfinished_training(_with(ckpt, {"max_epochs": 5}, 0, 13, 13)) == (
        "stopped in epoch 0 after 13 batches (global step 13) of a run set to train 5 epochs"
    )
    assert unfinished_training(_with(ckpt, {"max_epochs": 5}, 2, 0, 60)) == (
        "stopped in epoch 2 at its start (global step 60) of a run set to train 5 epochs"
    )
    assert unfinished_training(_with(ckpt, {"max_epochs": 5, "max_steps": 60}, 2, 0, 60)) is None  # max_steps
    assert unfinished_training(_with(ckpt, {"max_epochs": -1}, 2, 0, 60)) is None  # no end was set
    assert unfinished_training(_with(ckpt, {"fast_dev_run": True}, 1, 0, 1)).startswith("a fast_dev_run smoke run")


@pytest.mark.slow
def test_eval_of_an_unfinished_checkpoint_says_so_in_its_log_title_and_metrics(trained, tmp_path):
    ckpt = torch.load(trained[0], map_location="cpu", weights_only=True)
    stopped = tmp_path / "stopped.ckpt"
    torch.save(_with(ckpt, {"max_epochs": 5}, 0, 13, 13), stopped)
    out = tmp_path / "eval"
    proc = _run("src.eval", [f"ckpt_path={stopped}", f"hydra.run.dir={out}", "logger=none"])
    reason = "stopped in epoch 0 after 13 batches (global step 13) of a run set to train 5 epochs"
    assert f"{stopped} is from an unfinished training: {reason}" in proc.stdout
    assert f"Test metrics ({stopped}, eval grid level 3, refine=False; UNFINISHED training: {reason}):" in proc.stdout
    assert json.loads((out / "metrics.json").read_text())["unfinished"] == reason
    assert f"UNFINISHED training: {reason}" in (out / "metrics.md").read_text()
