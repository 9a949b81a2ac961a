"""Checkpoints that survive crashes, and resuming from them.

* ``last.ckpt`` exists as soon as the first epoch ends (a run killed then loses nothing);
* Ctrl-C and SIGTERM stop at a batch boundary, write ``last.ckpt`` and say how to resume; the resumed
  run ends with exactly the weights of the run that was never stopped;
* a full disk while writing leaves the previous ``last.ckpt`` intact;
* a resumed run takes its model, data and schedule from the checkpoint, the command line's explicit
  keys win; broken checkpoint files and invalid config values stop the run before any work;
* under SLURM, the requeue signal writes ``last.ckpt`` into the job's own directory and requeues the job,
  which continues from it.
"""

from __future__ import annotations

import random
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import lightning.pytorch as pl
import pytest
import torch
from torch import nn
from torch.utils.data import DataLoader, TensorDataset

from conftest import ENV, REPO, TINY, run_train, train_command
from image2sphere.testing.commands import process_group, run_group
from image2sphere.training.checkpoint import AtomicCheckpointIO, EpochCheckpoint

STEPS_PER_EPOCH_BS2 = 8  # 2 shapes x (10 - 2 validation) images in batches of 2


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("data")


@pytest.fixture(scope="module")
def trained(tmp_path_factory, data_dir) -> Path:
    """A one-epoch run with lmax 3 (not the TINY default); returns its run directory."""
    run = tmp_path_factory.mktemp("trained") / "run"
    run_train(["logger=none", "lmax=3", "trainer.max_epochs=1", f"hydra.run.dir={run}"], data_dir, run.parent / "logs")
    return run


def _wait_for(path: Path, proc: subprocess.Popen, timeout: float = 600) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists() and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.02)
    assert path.exists(), f"{path} was not written"


def _weights(run: Path) -> dict:
    return torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)


# ------------------------------------------------------------------ every epoch, kill, interrupt
@pytest.mark.slow
def test_sigkill_right_after_the_first_epoch_leaves_a_checkpoint_that_resumes_at_epoch_1(tmp_path, data_dir):
    run = tmp_path / "killed"
    cmd = train_command(["logger=none", "trainer.max_epochs=100", f"hydra.run.dir={run}"], data_dir, tmp_path / "l")
    ckpt = run / "checkpoints" / "last.ckpt"
    with process_group(cmd, cwd=REPO, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) as proc:
        _wait_for(ckpt, proc)  # leaving the block kills the whole run (SIGKILL)
    saved = torch.load(ckpt, map_location="cpu", weights_only=True)  # complete, plain types only
    steps = 3  # 2 shapes x 8 training images in batches of 6
    assert saved["epoch"] == 0 and saved["global_step"] == steps  # written when the first epoch ended
    assert not list(run.joinpath("checkpoints").glob("*.tmp-*"))
    resumed = tmp_path / "resumed"
    proc2 = run_train(
        ["logger=none", "trainer.max_epochs=2", f"ckpt_path={ckpt}", f"hydra.run.dir={resumed}"], data_dir, tmp_path
    )
    assert "Restored all states from the checkpoint" in proc2.stdout + proc2.stderr
    final = _weights(resumed)
    assert final["epoch"] == 1 and final["global_step"] == 2 * steps  # exactly epoch 1 was trained


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_interrupted_run_writes_last_ckpt_says_how_to_resume_and_resumes_exactly(tmp_path, data_dir, sig):
    # 3 epochs: a signal 0.1 s into epoch 1 lands before the end of training however fast the machine is,
    # in epoch 1 or, on a fast machine, in epoch 2 (with the fused optimiser epoch 1's 8 batches and its
    # validation took less than 0.5 s here: a stop 0.5 s in once landed at step 17). A stop in an epoch's
    # last batch or its validation waits for the epoch's end; a stop at the end of the last epoch would leave
    # the resumed run nothing to do, hence the bound below the last step.
    common = ["logger=none", "dataset.batch_size=2", "trainer.max_epochs=3"]
    full, stopped, resumed = tmp_path / "full", tmp_path / "stopped", tmp_path / "resumed"
    cmd = train_command([*common, f"hydra.run.dir={stopped}"], data_dir, tmp_path / "logs")
    ckpt = stopped / "checkpoints" / "last.ckpt"
    with process_group(cmd, cwd=REPO, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) as proc:
        _wait_for(ckpt, proc)  # the end of epoch 0
        time.sleep(0.1)  # into epoch 1
        proc.send_signal(sig)
        out, _ = proc.communicate(timeout=300)
    assert proc.returncode == 128 + sig, out[-3000:]
    assert f"Training stopped by {signal.Signals(sig).name}" in out
    assert f"Resume with: python -m src.train ckpt_path={ckpt}" in out
    assert not (stopped / "metrics.json").exists()  # no test after an interrupted fit
    saved = torch.load(ckpt, map_location="cpu", weights_only=True)
    assert STEPS_PER_EPOCH_BS2 <= saved["global_step"] < 3 * STEPS_PER_EPOCH_BS2  # after epoch 0, before the end

    run_train([*common, f"hydra.run.dir={full}"], data_dir, tmp_path / "logs")
    run_train(
        ["logger=none", "dataset.batch_size=2", f"ckpt_path={ckpt}", f"hydra.run.dir={resumed}"], data_dir, tmp_path
    )
    a, b = _weights(full), _weights(resumed)
    assert a["global_step"] == b["global_step"] == 3 * STEPS_PER_EPOCH_BS2
    for key, value in a["state_dict"].items():
        torch.testing.assert_close(b["state_dict"][key], value, rtol=1e-5, atol=1e-6, msg=f"weights differ: {key}")


# ------------------------------------------------------------------ atomic writes, full disk
class _Tiny(pl.LightningModule):
    def __init__(self):
        super().__init__()
        self.layer = nn.Linear(4, 1)

    def training_step(self, batch, batch_idx):
        return self.layer(batch[0]).pow(2).mean()

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


class _DiskFullFromEpoch(pl.Callback):
    """From the start of ``epoch`` on, no file of this process may grow past 64 bytes (EFBIG, like a full disk)."""

    def __init__(self, epoch: int):
        self.epoch = epoch

    def on_train_epoch_start(self, trainer, pl_module):
        if trainer.current_epoch == self.epoch:
            resource.setrlimit(resource.RLIMIT_FSIZE, (64, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))


def test_full_disk_while_saving_keeps_the_previous_last_ckpt(tmp_path):
    limits = resource.getrlimit(resource.RLIMIT_FSIZE)
    previous_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # writes fail with EFBIG instead
    data = DataLoader(TensorDataset(torch.randn(8, 4)), batch_size=4)
    checkpoint = EpochCheckpoint(dirpath=tmp_path / "checkpoints", save_last=True, save_top_k=0)
    trainer = pl.Trainer(
        max_epochs=3, callbacks=[checkpoint, _DiskFullFromEpoch(1)], plugins=[AtomicCheckpointIO()],
        logger=False, enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path,
    )  # fmt: skip
    last = tmp_path / "checkpoints" / "last.ckpt"
    try:
        with pytest.raises(OSError, match=r"could not write checkpoint .*last\.ckpt.*previous last\.ckpt is intact"):
            trainer.fit(_Tiny(), data)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, limits)
        signal.signal(signal.SIGXFSZ, previous_handler)
    saved = torch.load(last, weights_only=True)  # the epoch-0 checkpoint, whole
    assert saved["epoch"] == 0 and saved["global_step"] == 2
    assert sorted(p.name for p in last.parent.iterdir()) == ["last.ckpt"]  # no partial temporary file left


def test_atomic_write_replaces_the_file_only_when_complete(tmp_path):
    path = tmp_path / "last.ckpt"
    io = AtomicCheckpointIO()
    io.save_checkpoint({"step": 1, "w": torch.ones(3)}, path)
    before = path.read_bytes()

    class Unpicklable:
        def __reduce__(self):
            raise RuntimeError("boom while writing")

    with pytest.raises(RuntimeError, match="boom while writing"):
        io.save_checkpoint({"step": 2, "bad": Unpicklable()}, path)
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["last.ckpt"]
    io.save_checkpoint({"step": 3, "w": torch.zeros(3)}, path)
    assert torch.load(path, weights_only=True)["step"] == 3


# ------------------------------------------------------------------ resume from the checkpoint's config
@pytest.mark.slow
def test_resume_rebuilds_model_and_data_from_the_checkpoint_config(tmp_path, trained, data_dir):
    ckpt = trained / "checkpoints" / "last.ckpt"
    resumed = tmp_path / "resumed"
    # none of the original overrides (lmax 3, 32 px, tiny network ...) are repeated; lr is changed explicitly
    cmd = [sys.executable, "-m", "src.train", f"ckpt_path={ckpt}", "trainer.max_epochs=2", "model.optimizer.lr=0.5",
           "logger=none", f"paths.data_dir={data_dir}", f"paths.log_dir={tmp_path}", f"hydra.run.dir={resumed}",
           "callbacks.progress_bar.refresh_rate=0", "trainer.accelerator=cpu"]  # fmt: skip
    proc = run_group(cmd, cwd=REPO, env=ENV, timeout=600)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-4000:]
    assert "from the checkpoint's stored config" in out
    assert "from the command line: model.optimizer.lr, trainer.max_epochs" in out
    final = _weights(resumed)
    config = final["run_config"]
    assert config["lmax"] == 3 and config["model"]["net"]["lmax"] == 3 and config["dataset"]["image_size"] == 32
    assert config["model"]["net"]["sphere_channels"] == 16
    assert config["model"]["optimizer"]["lr"] == 0.5 and config["trainer"]["max_epochs"] == 2
    assert final["epoch"] == 1
    assert (resumed / "resumed_config.yaml").is_file()


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "is empty (0 bytes)"),
        (None, "is not a complete checkpoint"),  # the trained checkpoint cut in half
        (random.Random(0).randbytes(3000), "is not a complete checkpoint"),  # seeded: the same test id in every process
    ],
    ids=["empty", "truncated", "random bytes"],
)
def test_broken_checkpoint_is_refused_before_any_work(tmp_path, trained, data_dir, content, message):
    bad = tmp_path / "bad.ckpt"
    if content is None:
        whole = (trained / "checkpoints" / "last.ckpt").read_bytes()
        content = whole[: len(whole) // 2]
    bad.write_bytes(content)
    proc = run_train(["logger=none", f"ckpt_path={bad}", f"hydra.run.dir={tmp_path / 'run'}"], data_dir, tmp_path,
                     check=False)  # fmt: skip
    assert proc.returncode != 0 and f"{bad} {message}" in proc.stderr, proc.stderr[-3000:]
    assert "weights_only=False" not in proc.stderr and "Traceback" not in proc.stderr.split("Error")[0]
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_foreign_checkpoint_is_refused(tmp_path, data_dir):
    foreign = tmp_path / "foreign.ckpt"
    torch.save({"weights": torch.ones(2)}, foreign)
    proc = run_train(["logger=none", f"ckpt_path={foreign}"], data_dir, tmp_path, check=False)
    assert proc.returncode != 0 and "is not a Lightning checkpoint" in proc.stderr


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("eval_grid_level=9", "eval_grid_level=9 is too fine"),
        ("train_grid_level=-1", "train_grid_level must be an integer"),
        ("lmax=-2", "lmax must be an integer >= 0"),
        ("dataset.batch_size=0", "dataset.batch_size must be an integer >= 1"),
        ("model.net.image_size=64", "model.net.image_size=64 but dataset.image_size=32"),
        ("seed=1.5", "seed must be an integer or null"),
    ],
)
def test_invalid_config_values_stop_the_run_before_any_work(tmp_path, override, message):
    data = tmp_path / "data"
    start = time.monotonic()
    proc = run_train(["logger=none", override], data, tmp_path / "logs", check=False)
    assert proc.returncode != 0 and message in proc.stderr, proc.stderr[-3000:]
    assert time.monotonic() - start < 60
    assert not data.exists() or not any(data.iterdir())  # nothing was rendered


# ------------------------------------------------------------------ fast_dev_run writes nothing heavy
def test_fast_dev_run_writes_no_checkpoint_and_no_logger_files(tmp_path, data_dir):
    run = tmp_path / "run"
    run_train(["trainer.fast_dev_run=true", "logger=wandb", f"hydra.run.dir={run}"], data_dir, tmp_path)
    assert (run / "metrics.json").is_file()
    assert not list(run.rglob("*.ckpt")) and not (run / "wandb").exists()


# ------------------------------------------------------------------ SLURM requeue
SLURM = {"SLURM_JOB_ID": "4242", "SLURM_NTASKS": "1", "SLURM_JOB_NAME": "i2s", "SLURM_PROCID": "0",
         "SLURM_LOCALID": "0", "SLURM_NODEID": "0", "SLURM_NODELIST": "localhost"}  # fmt: skip


@pytest.mark.slow
def test_slurm_requeue_signal_writes_last_ckpt_requeues_and_the_requeued_job_resumes_from_it(tmp_path, data_dir):
    """The requeue signal takes the path of SIGTERM (the ranks decide, last.ckpt is written) and then asks
    SLURM to requeue the job; the requeued job (same id, a restart counted) continues in its directory."""
    env = {**ENV, **SLURM, "PATH": f"{tmp_path}:{ENV['PATH']}"}
    (tmp_path / "scontrol").write_text('#!/bin/sh\necho "$@" >> "$(dirname "$0")/requeued"\n')
    (tmp_path / "scontrol").chmod(0o755)
    logs = tmp_path / "logs"
    cmd = train_command(["logger=none", "trainer.max_epochs=100"], data_dir, logs)
    run = logs / "train" / "runs" / "slurm_4242"  # named after the job, so a requeued job finds it
    ckpt = run / "checkpoints" / "last.ckpt"
    with process_group(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) as proc:
        _wait_for(ckpt, proc)
        time.sleep(0.3)  # into the next epoch
        proc.send_signal(signal.SIGUSR1)
        out, _ = proc.communicate(timeout=300)
    assert proc.returncode == 128 + signal.SIGUSR1, out[-3000:]
    assert "SLURM requeues the job; it continues from that checkpoint" in out, out[-3000:]
    assert (tmp_path / "requeued").read_text().split() == ["requeue", "4242"]
    assert not list(run.glob("hpc_ckpt_*.ckpt"))  # one checkpoint, one mechanism
    saved = torch.load(ckpt, map_location="cpu", weights_only=True)
    env["SLURM_RESTART_COUNT"] = "1"
    max_epochs = saved["epoch"] + 2
    cmd = train_command(["logger=none", f"trainer.max_epochs={max_epochs}"], data_dir, logs)
    proc2 = run_group(cmd, cwd=REPO, env=env, timeout=600)
    out = proc2.stdout + proc2.stderr
    assert proc2.returncode == 0, out[-4000:]
    assert f"Requeued SLURM job 4242: continuing from {ckpt}" in out
    assert (run / "metrics.json").is_file() and _weights(run)["epoch"] == max_epochs - 1


def test_tiny_overrides_are_the_ones_the_entry_test_uses():
    assert "dataset.image_size=32" in TINY and "lmax=2" in TINY  # the trained fixture's lmax 3 differs from these


def test_checkpoint_from_before_projector_normalization_keeps_its_rule(tmp_path, trained):
    """Checkpoints written before model.net.projector_normalization existed were trained with sum / sqrt(n)."""
    from image2sphere.training.checkpoint import build_module, load_checkpoint

    ckpt = torch.load(trained / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert ckpt["run_config"]["model"]["net"]["projector_normalization"] == "mean"  # today's default
    del ckpt["run_config"]["model"]["net"]["projector_normalization"]
    old = tmp_path / "old.ckpt"
    torch.save(ckpt, old)
    loaded = load_checkpoint(old)
    assert loaded["run_config"]["model"]["net"]["projector_normalization"] == "sqrt"
    assert build_module(loaded, old).net.projector.normalization == "sqrt"
    current = load_checkpoint(trained / "checkpoints" / "last.ckpt")
    assert build_module(current, "current").net.projector.normalization == "mean"


def test_i2s_checkpoint_from_before_the_relu_grid_rule_keeps_resolution_8(tmp_path, trained):
    """Before ``activation_resolution`` followed the band limit, I2S's ReLU grid was 8 at every lmax. A
    stored config without the key gets 8 (at lmax 10 today's rule would give 12), and loading a checkpoint
    applies it: the trained fixture's network (lmax 3) is rebuilt with that grid."""
    from image2sphere.nn import SO3ReLU
    from image2sphere.nn.activation import default_relu_resolution
    from image2sphere.training.checkpoint import _upgrade_run_config, build_module, load_checkpoint

    stored = {"model": {"net": {"_target_": "image2sphere.nn.I2S", "lmax": 10, "projector_normalization": "mean"}}}
    _upgrade_run_config(stored, tmp_path / "stored.ckpt")
    assert stored["model"]["net"]["activation_resolution"] == 8 != default_relu_resolution(10)

    ckpt = torch.load(trained / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    net_cfg = ckpt["run_config"]["model"]["net"]
    del net_cfg["activation_resolution"]
    old = tmp_path / "old.ckpt"
    torch.save(ckpt, old)
    loaded = load_checkpoint(old)
    assert loaded["run_config"]["model"]["net"]["activation_resolution"] == 8
    relus = [m for m in build_module(loaded, old).net.modules() if isinstance(m, SO3ReLU)]
    assert relus and all(m.resolution == 8 for m in relus)


def test_fourier_mlp_checkpoint_from_before_degree_power_predicts_as_it_was_trained(tmp_path):
    """A Fourier MLP checkpoint written before ``model.net.degree_power`` existed held the coefficients as
    the last layer gave them (power 0); rebuilt today it must predict exactly that, not today's default 1.
    Quick: a 32 px network built from the real config, no training."""
    from hydra import compose, initialize
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from image2sphere.training.checkpoint import build_module, load_checkpoint

    with initialize(version_base="1.3", config_path="../conf"):
        cfg = compose(config_name="train", overrides=["model=fourier_mlp", "lmax=2", "dataset.image_size=32"])
    model_cfg = OmegaConf.to_container(cfg.model, resolve=True)
    assert model_cfg["net"]["degree_power"] == 1.0  # today's default
    torch.manual_seed(0)
    module = instantiate(OmegaConf.create(model_cfg))
    with torch.no_grad():  # weights in the zero-initialised last layer, so that a scale would show
        module.net.mlp[-1].weight.normal_()
    del model_cfg["net"]["degree_power"]  # as a run of the earlier code stored it
    path = tmp_path / "old.ckpt"
    torch.save({"state_dict": module.state_dict(), "run_config": {"model": model_cfg}}, path)

    loaded = load_checkpoint(path)
    assert loaded["run_config"]["model"]["net"]["degree_power"] == 0.0
    rebuilt = build_module(loaded, path).net
    images = torch.randn(2, 3, 32, 32)
    with torch.no_grad():
        as_trained = rebuilt.mlp(rebuilt.pooled_features(images))  # the coefficients the last layer gives
        assert torch.equal(rebuilt(images), as_trained)
        assert not torch.allclose(module.net(images), as_trained)  # today's default would predict otherwise


def test_i2s_checkpoint_from_before_input_scaling_predicts_as_it_was_trained(tmp_path):
    """An I2S checkpoint written before ``model.net.input_scaling`` existed fed its encoder the
    ImageNet-normalised images: its stored config gets ``imagenet`` and the rebuilt network predicts
    exactly what it did, where ``unit`` would predict otherwise. Quick: a 32 px network from the real
    config, no training."""
    from hydra import compose, initialize
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from image2sphere.training.checkpoint import _upgrade_run_config, build_module, load_checkpoint

    overrides = ["lmax=2", "dataset.image_size=32", "model.net.sphere_channels=8", "model.net.output_init=random"]
    with initialize(version_base="1.3", config_path="../conf"):
        cfg = compose(config_name="train", overrides=overrides)
    model_cfg = OmegaConf.to_container(cfg.model, resolve=True)
    assert model_cfg["net"]["input_scaling"] == "imagenet"  # today's default
    torch.manual_seed(0)
    module = instantiate(OmegaConf.create(model_cfg)).eval()
    del model_cfg["net"]["input_scaling"]  # as a run of the earlier code stored it
    path = tmp_path / "old.ckpt"
    torch.save({"state_dict": module.state_dict(), "run_config": {"model": model_cfg}}, path)

    loaded = load_checkpoint(path)
    assert loaded["run_config"]["model"]["net"]["input_scaling"] == "imagenet"
    rebuilt = build_module(loaded, path).net.eval()
    assert rebuilt.input_scaling == "imagenet"
    images = torch.randn(2, 3, 32, 32)
    with torch.no_grad():
        as_trained = module.net(images)
        assert torch.equal(rebuilt(images), as_trained)
        rebuilt.input_scaling = "unit"
        assert not torch.allclose(rebuilt(images), as_trained)  # the other scaling would predict otherwise
    stored = {"model": {"net": {"_target_": "image2sphere.nn.I2S", "input_scaling": "unit"}}}
    _upgrade_run_config(stored, tmp_path / "stored.ckpt")
    assert stored["model"]["net"]["input_scaling"] == "unit"  # a stored value is kept
