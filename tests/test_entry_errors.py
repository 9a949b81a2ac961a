"""What the entry points do when a start is refused (:mod:`image2sphere.training.entry`): one line naming the
key and exit status 1 (the full traceback with ``HYDRA_FULL_ERROR=1``), no run directory left behind, a bad
job of a multirun failing alone; and what is a user's error and what keeps its traceback."""

from __future__ import annotations

import logging
import re
import sys
from pathlib import Path

import pytest
from hydra.conf import HydraConf
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from hydra.utils import instantiate
from omegaconf import OmegaConf

from conftest import ENV, caught, run_module, run_train
from image2sphere.training import entry
from image2sphere.training.entry import discard_failed_start, refusal


def _command(module: str, *args: str) -> list[str]:
    return [sys.executable, "-m", module, *args]


# ------------------------------------------------------------------------------------- one line
@pytest.mark.parametrize(
    ("module", "args", "line"),
    [
        ("src.train", ["lmax=-1", "logger=none"], "Error: lmax must be an integer >= 0, got -1"),
        ("src.train", ["ckpt_path=/nonexistent/last.ckpt", "logger=none"],
         "Error: ckpt_path=/nonexistent/last.ckpt does not exist; pass the checkpoint of an earlier run, "
         "e.g. ckpt_path=logs/train/runs/<run>/checkpoints/last.ckpt"),
        ("src.eval", [], "Error: ckpt_path is required: python -m src.eval "
         "ckpt_path=logs/train/runs/<run>/checkpoints/last.ckpt"),
        ("src.predict", [], "Error: ckpt_path is required: give it on the command line (ckpt_path=...)"),
    ],
    ids=["train lmax", "train ckpt_path", "eval", "predict"],
)  # fmt: skip
def test_a_refused_value_is_one_line_and_leaves_no_run_directory(tmp_path, module, args, line):
    proc = run_module(_command(module, *args, f"paths.log_dir={tmp_path / 'logs'}"), check=False)
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.strip().splitlines() == [line], proc.stderr
    task = module.split(".")[1]
    runs = tmp_path / "logs" / task / "runs"
    assert runs.is_dir() and list(runs.iterdir()) == []  # Hydra made the run directory; the refusal removed it


def test_hydra_full_error_shows_the_traceback(tmp_path):
    proc = run_module(_command("src.train", "lmax=-1", "logger=none", f"paths.log_dir={tmp_path}"),
                      env={**ENV, "HYDRA_FULL_ERROR": "1"}, check=False)  # fmt: skip
    assert proc.returncode == 1
    assert "Traceback (most recent call last)" in proc.stderr and "check_train_config" in proc.stderr, proc.stderr
    assert proc.stderr.rstrip().endswith("ConfigError: lmax must be an integer >= 0, got -1"), proc.stderr[-500:]
    assert not any((tmp_path / "train" / "runs").iterdir())  # the directory is removed all the same


def test_a_bug_before_the_training_loop_keeps_its_traceback_and_its_run_directory(tmp_path):
    """Quick. A callback whose construction fails with a ``TypeError`` (a bug, not a refusal), as
    ``python -m src.train`` builds the trainer before any loop: Hydra's report with the traceback, exit status 1,
    and the run directory with its config and log left for the report (it used to be removed)."""
    run = tmp_path / "run"
    args = ["+callbacks.broken._target_=builtins.int", "+callbacks.broken.not_a_keyword=1", "logger=none",
            f"hydra.run.dir={run}"]  # fmt: skip
    proc = run_train(args, tmp_path / "data", tmp_path / "logs", check=False)
    assert proc.returncode == 1, proc.stderr
    assert "Error: " not in proc.stderr and "not_a_keyword" in proc.stderr, proc.stderr  # no refusal line
    assert (run / ".hydra" / "config.yaml").is_file() and (run / "train.log").is_file()


def test_a_refused_start_in_an_empty_directory_that_existed_leaves_it_as_it_was(tmp_path):
    run_dir = tmp_path / "mine"
    run_dir.mkdir()
    proc = run_module(_command("src.train", "lmax=-1", "logger=none", f"hydra.run.dir={run_dir}"), check=False)
    assert proc.returncode == 1 and proc.stderr.strip() == "Error: lmax must be an integer >= 0, got -1"
    assert run_dir.is_dir() and list(run_dir.iterdir()) == []  # Hydra's files gone, the folder kept


# ------------------------------------------------------------------------------------- user error or bug
def _raise(exc: BaseException):
    raise exc


def test_a_refusal_is_one_of_the_projects_refusal_types():
    """Quick. The three refusal types (the checks', a missing input, an output that exists), also wrapped by
    Hydra's instantiation, and a required key left out: their messages as they are."""
    from image2sphere.checks import InputNotFoundError, OutputExistsError, check_int
    from image2sphere.data.common import DatasetNotFoundError
    from image2sphere.training.checkpoint import CheckpointError

    assert refusal(caught(check_int, "dataset.batch_size", 0, 1)) == "dataset.batch_size must be an integer >= 1, got 0"
    assert refusal(caught(_raise, InputNotFoundError("data/x not found: get it from y"))) == (
        "data/x not found: get it from y"
    )
    assert refusal(caught(_raise, OutputExistsError("out.png exists"))) == "out.png exists"
    for kind in (DatasetNotFoundError, CheckpointError):  # the readers' own types are refusals too
        assert refusal(caught(_raise, kind("m"))) == "m"
    # raised while Hydra instantiated a node (a data module that finds no dataset): the reader's message
    node = {"_target_": "image2sphere.checks.check_int", "name": "k", "value": -1}
    assert refusal(caught(instantiate, node)) == "k must be an integer >= 0, got -1"
    missing = OmegaConf.create({"image": "???"})
    assert refusal(caught(lambda: missing.image)) == "image is required: give it on the command line (image=...)"


BUGS = [ValueError("operands could not be broadcast"), FileNotFoundError("x"), FileExistsError("y"),
        RuntimeError("shapes"), TypeError("x"), KeyError("k")]  # fmt: skip


@pytest.mark.parametrize("exc", BUGS)
def test_a_bug_keeps_its_traceback_and_its_run_directory(exc, job_dir):
    """Quick. Any other exception, the built-in types the refusals extend included (raised by torch, numpy,
    or a line of ours that is no check): no one-line message, and the run directory stays for its report."""
    run = job_dir(RunMode.RUN)
    assert refusal(caught(_raise, exc)) is None
    assert not discard_failed_start(caught(_raise, exc)) and (run / ".hydra" / "config.yaml").is_file()


# ------------------------------------------------------------------------------------- what is removed
@pytest.fixture
def job_dir(tmp_path):
    """A Hydra job's directory as Hydra leaves it before the task (``.hydra/`` and the log, whose file handler
    is attached), with HydraConfig set for it; ``job_dir.set(mode)`` picks run or multirun."""
    run = tmp_path / "job"
    (run / ".hydra").mkdir(parents=True)
    for name in ("config.yaml", "hydra.yaml", "overrides.yaml"):
        (run / ".hydra" / name).write_text("{}\n")
    handler = logging.FileHandler(run / "train.log")
    logging.getLogger().addHandler(handler)
    logging.getLogger().warning("a line of the job's log")

    def set_mode(mode: RunMode, new: bool = True) -> Path:
        cfg = OmegaConf.create({"hydra": OmegaConf.structured(HydraConf)})
        cfg.hydra.runtime.output_dir = str(run)
        cfg.hydra.mode = mode
        HydraConfig.instance().set_config(cfg)
        if new:
            entry._NEW_RUN_DIRS.add(str(run))
        return run

    try:
        yield set_mode
    finally:
        HydraConfig.instance().cfg = None
        entry._NEW_RUN_DIRS.discard(str(run))
        logging.getLogger().removeHandler(handler)
        handler.close()


def _refused() -> ValueError:
    """A refusal as the config check raises it."""
    from image2sphere.checks import ConfigError

    return ConfigError("lmax must be an integer >= 0, got -1")


@pytest.mark.parametrize("mode", [RunMode.RUN, RunMode.MULTIRUN])
def test_a_failed_start_removes_its_own_directory(job_dir, mode):
    run = job_dir(mode)
    assert discard_failed_start(_refused()) and not run.exists()


def test_a_run_directory_that_existed_keeps_the_folder(job_dir):
    run = job_dir(RunMode.RUN, new=False)  # e.g. an empty hydra.run.dir made by the user
    assert not discard_failed_start(_refused())
    assert run.is_dir() and list(run.iterdir()) == []


@pytest.mark.parametrize(
    "written", ["metrics.json", "checkpoints/last.ckpt", "csv/version_0/metrics.csv", ".hydra/extra.yaml"]
)
def test_nothing_is_removed_where_anything_else_was_written(job_dir, written):
    run = job_dir(RunMode.MULTIRUN)
    (run / written).parent.mkdir(parents=True, exist_ok=True)
    (run / written).write_text("x")
    before = sorted(p.relative_to(run) for p in run.rglob("*"))
    assert not discard_failed_start(_refused())
    assert sorted(p.relative_to(run) for p in run.rglob("*")) == before
    assert "a line of the job's log" in (run / "train.log").read_text()


def test_nothing_is_removed_on_another_rank_or_once_a_loop_ran(job_dir, monkeypatch):
    run = job_dir(RunMode.RUN)
    monkeypatch.setitem(entry._LOOP, "started", False)
    entry.note_loop_start()  # a trainer's loop began (NoteLoopStart)
    assert not discard_failed_start(_refused()) and (run / ".hydra" / "config.yaml").is_file()
    entry._LOOP["started"] = False
    monkeypatch.setenv("LOCAL_RANK", "1")  # a DDP rank Lightning started: rank 0 owns the directory
    assert not discard_failed_start(_refused()) and (run / "train.log").is_file()


# ------------------------------------------------------------------------------------- a multirun
@pytest.mark.slow
def test_a_refused_job_of_a_multirun_fails_alone(tmp_path):
    """``-m lmax=-1,2``: job 0 is refused (its directory removed), job 1 still runs; Hydra reports the
    failed job after the sweep in its compact form, and the exit status is 1."""
    sweep = tmp_path / "sweep"
    proc = run_train(["-m", "lmax=-1,2", "trainer.fast_dev_run=true", "logger=none", f"hydra.sweep.dir={sweep}"],
                     tmp_path / "data", tmp_path / "logs", check=False)  # fmt: skip
    assert proc.returncode == 1, proc.stderr[-3000:]
    assert not (sweep / "0").exists() and (sweep / "1" / "metrics.json").is_file()
    assert "Error: lmax must be an integer >= 0, got -1" in proc.stdout  # logged when the job failed
    assert re.search(r"Error executing job with overrides: \[.*'lmax=-1'", proc.stderr), proc.stderr[-3000:]
    assert "\nError: lmax must be an integer >= 0, got -1\n" in proc.stderr and "Traceback" not in proc.stderr


# ------------------------------------------------------------------------------------- the checkpoint given
def _run_with_checkpoints(root: Path) -> Path:
    """A run directory with ``checkpoints/last.ckpt`` and an older ``epoch=0-step=3.ckpt`` (files the check never
    opens)."""
    import os

    run = root / "runs" / "a_run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "epoch=0-step=3.ckpt").write_bytes(b"x")
    (run / "checkpoints" / "last.ckpt").write_bytes(b"x")
    os.utime(run / "checkpoints" / "last.ckpt", (1, 1))  # older than the epoch file: last.ckpt still comes first
    return run


def test_a_directory_as_ckpt_path_names_the_checkpoints_in_it(tmp_path):
    from image2sphere.training.checkpoint import checkpoint_file

    run = _run_with_checkpoints(tmp_path)
    last = run / "checkpoints" / "last.ckpt"
    with pytest.raises(FileNotFoundError) as refused:
        checkpoint_file(run)
    assert str(refused.value) == (
        f"ckpt_path={run} is a directory; pass a checkpoint file, e.g. ckpt_path={last} "
        "(also there: checkpoints/epoch=0-step=3.ckpt)"
    )
    with pytest.raises(FileNotFoundError, match=rf"^ckpt_path={run.parent} is a directory; .* ckpt_path={last} "):
        checkpoint_file(run.parent)  # a folder of runs: their checkpoints/
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match=r"is a directory and holds no checkpoint"):
        checkpoint_file(tmp_path / "empty")
    assert checkpoint_file(last) == last


@pytest.mark.parametrize("module", ["src.train", "src.eval", "src.predict"])
def test_every_entry_point_refuses_a_directory_as_ckpt_path_in_one_line(tmp_path, module):
    run = _run_with_checkpoints(tmp_path)
    image = tmp_path / "image.png"
    image.write_bytes(b"")
    extra = [f"image={image}"] if module == "src.predict" else ["logger=none"]
    proc = run_module(_command(module, f"ckpt_path={run}", *extra, f"paths.log_dir={tmp_path / 'logs'}"), check=False)
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.splitlines() == [
        f"Error: ckpt_path={run} is a directory; pass a checkpoint file, e.g. ckpt_path={run}/checkpoints/last.ckpt "
        "(also there: checkpoints/epoch=0-step=3.ckpt)"
    ]
    assert "Seed set" not in proc.stdout + proc.stderr  # the refusal comes before any seeding
    assert not any((tmp_path / "logs" / module.split(".")[1] / "runs").iterdir())


# ------------------------------------------------------------------------------------- another model
def _fake_run(root: Path, model: str) -> Path:
    """The path of ``last.ckpt`` in a run directory whose ``.hydra/`` says it trained ``model=<model>``."""
    run = root / "run"
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").write_text("model: {}\n")
    (run / ".hydra" / "hydra.yaml").write_text(f"hydra:\n  runtime:\n    choices:\n      model: {model}\n")
    (run / ".hydra" / "overrides.yaml").write_text("[]\n")
    return run / "checkpoints" / "last.ckpt"


I2S = {"_target_": "image2sphere.training.PoseEstimationModule", "net": {"_target_": "image2sphere.nn.I2S"}}
FLOW = {"_target_": "image2sphere.training.PoseEstimationModule", "net": {"_target_": "image2sphere.nn.RotationFlow"}}
CHANGED = {"model.net._target_", "model.net.lmax"}  # what the command line changed, as Hydra composes it


def test_a_model_option_other_than_the_checkpoints_is_refused(tmp_path):
    from image2sphere.training.run_config import check_same_model

    ckpt = str(_fake_run(tmp_path, "i2s"))
    with pytest.raises(ValueError) as refused:
        check_same_model({"model": I2S}, {"model": FLOW}, ["model=rotation_flow", "lmax=4"], CHANGED, ckpt)
    assert str(refused.value) == (
        f"ckpt_path={ckpt} holds a model=i2s run; model=rotation_flow cannot continue it: drop model=rotation_flow "
        "to resume it, or leave out ckpt_path to train a new model"
    )
    with pytest.raises(ValueError, match="holds a model=i2s run; model=i2s_spatial_filter cannot"):  # same classes
        check_same_model({"model": I2S}, {"model": I2S}, ["model=i2s_spatial_filter"], {"model.net.filter"}, ckpt)
    check_same_model({"model": I2S}, {"model": I2S}, ["model=i2s", "trainer.max_epochs=9"], set(), ckpt)
    check_same_model({"model": I2S}, {"model": I2S}, [], set(), ckpt)  # the checkpoint's own model


def test_without_its_run_directory_the_checkpoints_network_class_decides(tmp_path):
    from image2sphere.training.run_config import check_same_model

    copied = str(tmp_path / "copied.ckpt")  # no .hydra/ above it: its model= option is unknown
    with pytest.raises(ValueError) as refused:
        check_same_model({"model": I2S}, {"model": FLOW}, ["model=rotation_flow"], CHANGED, copied)
    assert str(refused.value) == (
        f"ckpt_path={copied} holds a run of I2S (model.net._target_); model=rotation_flow (RotationFlow) cannot "
        "continue it: drop model=rotation_flow to resume it, or leave out ckpt_path to train a new model"
    )
    check_same_model({"model": I2S}, {"model": I2S}, ["model=i2s_spatial_filter"], {"model.net.filter"}, copied)


def test_weights_that_do_not_fit_name_a_few_parameters_in_one_line():
    import torch

    from image2sphere.training.checkpoint import CheckpointError, check_resumed_weights

    built = torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.Linear(8, 2))
    saved = torch.nn.Sequential(torch.nn.Linear(4, 16), torch.nn.Linear(16, 2), torch.nn.Linear(2, 2))
    with pytest.raises(CheckpointError) as refused:
        check_resumed_weights(built, {"state_dict": saved.state_dict()}, "x/last.ckpt")
    assert str(refused.value) == (
        "ckpt_path=x/last.ckpt does not fit the network this command line builds: 2 parameters unexpected (2.bias, "
        "2.weight); 3 parameters of another shape (0.bias (16,) vs (8,), 0.weight (16, 4) vs (8, 4), 1.weight "
        "(2, 16) vs (2, 8)); resume without the model.* overrides that change the network's shape, or leave out "
        "ckpt_path to train a new model"
    )
    check_resumed_weights(built, {"state_dict": built.state_dict()}, "x/last.ckpt")


@pytest.mark.slow
def test_resuming_with_another_model_or_network_size_is_one_line_before_training(tiny_run, tmp_path):
    """The real entry point on the tiny run's checkpoint: ``model=rotation_flow`` is refused before anything is
    built, ``model.net.sphere_channels=32`` once the network is built; neither leaves a run directory."""
    ckpt = tiny_run / "checkpoints" / "last.ckpt"
    logs = tmp_path / "logs"
    other = run_module(_command("src.train", f"ckpt_path={ckpt}", "model=rotation_flow", "logger=none",
                                f"paths.log_dir={logs}"), check=False)  # fmt: skip
    assert other.returncode == 1, other.stderr[-3000:]
    assert other.stderr.splitlines() == [
        f"Error: ckpt_path={ckpt} holds a model=i2s run; model=rotation_flow cannot continue it: drop "
        "model=rotation_flow to resume it, or leave out ckpt_path to train a new model"
    ]
    wider = run_train(["model.net.sphere_channels=32", f"ckpt_path={ckpt}", "logger=none"], tmp_path / "data", logs,
                      check=False)  # fmt: skip
    assert wider.returncode == 1, wider.stderr[-3000:]
    # the run's log before it (Lightning's "Seed set to 0"), then the one line; not Lightning's list of every key
    assert "Missing key" not in wider.stderr and "Traceback" not in wider.stderr, wider.stderr[-3000:]
    line = wider.stderr.splitlines()[-1]
    assert line.startswith(f"Error: ckpt_path={ckpt} does not fit the network this command line builds: ")
    assert "net.s2_conv.weight (16, 4, 9) vs (32, 4, 9)" in line
    assert not any((logs / "train" / "runs").iterdir())
