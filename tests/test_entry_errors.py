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

from conftest import ENV, run_module, run_train
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
    assert proc.stderr.rstrip().endswith("ValueError: lmax must be an integer >= 0, got -1"), proc.stderr[-500:]
    assert not any((tmp_path / "train" / "runs").iterdir())  # the directory is removed all the same


def test_a_refused_start_in_an_empty_directory_that_existed_leaves_it_as_it_was(tmp_path):
    run_dir = tmp_path / "mine"
    run_dir.mkdir()
    proc = run_module(_command("src.train", "lmax=-1", "logger=none", f"hydra.run.dir={run_dir}"), check=False)
    assert proc.returncode == 1 and proc.stderr.strip() == "Error: lmax must be an integer >= 0, got -1"
    assert run_dir.is_dir() and list(run_dir.iterdir()) == []  # Hydra's files gone, the folder kept


# ------------------------------------------------------------------------------------- user error or bug
def _raiser(module: str, code: str):
    """A function whose frame belongs to ``module`` (``__name__``), raising what ``code`` raises."""
    namespace = {"__name__": module}
    exec(f"def f(inner=None):\n    if inner: inner()\n    {code}\n", namespace)
    return namespace["f"]


def _caught(function, *args) -> BaseException:
    try:
        function(*args)
    except BaseException as e:  # noqa: BLE001 (the test looks at whatever it raised)
        return e
    raise AssertionError("nothing raised")


def test_a_refusal_is_a_value_or_file_error_of_the_projects_code_before_any_loop():
    from image2sphere.checks import check_int

    assert (
        refusal(_caught(check_int, "dataset.batch_size", 0, 1)) == "dataset.batch_size must be an integer >= 1, got 0"
    )
    ours_file = _raiser("image2sphere.data.fake", "raise FileNotFoundError('data/x not found: get it from y')")
    assert refusal(_caught(ours_file)) == "data/x not found: get it from y"
    # raised while Hydra instantiated a node (a data module that finds no dataset): the reader's message
    node = {"_target_": "image2sphere.checks.check_int", "name": "k", "value": -1}
    assert refusal(_caught(instantiate, node)) == "k must be an integer >= 0, got -1"
    missing = OmegaConf.create({"image": "???"})
    assert refusal(_caught(lambda: missing.image)) == "image is required: give it on the command line (image=...)"


def test_a_bug_keeps_its_traceback():
    # a ValueError of another library (torch, numpy...), reached from our code
    library = _raiser("numpy.fake", "raise ValueError('operands could not be broadcast')")
    assert refusal(_caught(_raiser("image2sphere.nn.fake", "pass"), library)) is None
    # any other type raised by our code
    assert refusal(_caught(_raiser("image2sphere.nn.fake", "raise RuntimeError('shapes')"))) is None
    assert refusal(_caught(_raiser("image2sphere.nn.fake", "raise TypeError('x')"))) is None
    # our ValueError inside a training loop: the run had started, more likely a bug than a setting
    ours = _raiser("image2sphere.training.fake", "raise ValueError('NaN in batch 3')")
    loop = _raiser("lightning.pytorch.loops.fake", "pass")
    assert refusal(_caught(loop, ours)) is None
    assert refusal(_caught(ours)) == "NaN in batch 3"  # the same error outside a loop is a refusal


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


REFUSED = ValueError("lmax must be an integer >= 0, got -1")


@pytest.mark.parametrize("mode", [RunMode.RUN, RunMode.MULTIRUN])
def test_a_failed_start_removes_its_own_directory(job_dir, mode):
    run = job_dir(mode)
    assert discard_failed_start(REFUSED) and not run.exists()


def test_a_run_directory_that_existed_keeps_the_folder(job_dir):
    run = job_dir(RunMode.RUN, new=False)  # e.g. an empty hydra.run.dir made by the user
    assert not discard_failed_start(REFUSED)
    assert run.is_dir() and list(run.iterdir()) == []


@pytest.mark.parametrize(
    "written", ["metrics.json", "checkpoints/last.ckpt", "csv/version_0/metrics.csv", ".hydra/extra.yaml"]
)
def test_nothing_is_removed_where_anything_else_was_written(job_dir, written):
    run = job_dir(RunMode.MULTIRUN)
    (run / written).parent.mkdir(parents=True, exist_ok=True)
    (run / written).write_text("x")
    before = sorted(p.relative_to(run) for p in run.rglob("*"))
    assert not discard_failed_start(REFUSED)
    assert sorted(p.relative_to(run) for p in run.rglob("*")) == before
    assert "a line of the job's log" in (run / "train.log").read_text()


def test_nothing_is_removed_on_another_rank_or_once_a_loop_ran(job_dir, monkeypatch):
    run = job_dir(RunMode.RUN)
    in_loop = _caught(_raiser("lightning.pytorch.loops.fake", "pass"), lambda: (_ for _ in ()).throw(REFUSED))
    assert not discard_failed_start(in_loop) and (run / ".hydra" / "config.yaml").is_file()
    monkeypatch.setenv("LOCAL_RANK", "1")  # a DDP rank Lightning started: rank 0 owns the directory
    assert not discard_failed_start(REFUSED) and (run / "train.log").is_file()


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
