"""What a run's terminal shows: the libraries' known-harmless messages silenced at their source (and only
those), one metrics table, and the job's log ending as the terminal does. Quick tier: about 1 s besides the
session's ``tiny_run``."""

from __future__ import annotations

import logging
import re
import warnings
from pathlib import Path
from unittest import mock

import lightning.pytorch as pl
import pytest
from lightning.pytorch.loggers import CSVLogger
from lightning.pytorch.loggers import WandbLogger as LightningWandbLogger

from image2sphere.training import terminal
from image2sphere.training.terminal import WandbLogger, quiet_known_noise, report

RANK_ZERO = "lightning.pytorch.utilities.rank_zero"


class _Records(logging.Handler):
    def __init__(self):
        super().__init__(logging.DEBUG)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


@pytest.fixture
def rank_zero_records():
    """The messages Lightning's rank-zero logger lets through during the test (its filters restored after)."""
    logger = logging.getLogger(RANK_ZERO)
    handler, filters, level = _Records(), list(logger.filters), logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    for f in filters:
        logger.removeFilter(f)
    yield logger, handler.messages
    logger.removeHandler(handler)
    logger.setLevel(level)
    for f in list(logger.filters):
        logger.removeFilter(f)
    for f in filters:
        logger.addFilter(f)


def _trainer(tmp_path: Path) -> None:
    pl.Trainer(logger=CSVLogger(tmp_path), accelerator="cpu", enable_progress_bar=False, enable_model_summary=False)


def test_lightnings_litlogger_tip_is_dropped_and_its_other_messages_are_not(rank_zero_records, tmp_path):
    logger, messages = rank_zero_records
    _trainer(tmp_path)  # Lightning as installed: the tip is there to drop (this fails once Lightning drops it)
    assert any(m.startswith("💡 Tip:") and "litlogger" in m for m in messages)
    messages.clear()
    quiet_known_noise()
    quiet_known_noise()  # idempotent: one filter
    assert logger.filters.count(terminal._TIP_FILTER) == 1
    _trainer(tmp_path)
    assert messages == ["GPU available: False, used: False", "TPU available: False, using: 0 TPU cores"]


def _leafspec_warnings() -> list[warnings.WarningMessage]:
    from lightning.pytorch.utilities._pytree import _tree_flatten

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _tree_flatten(1.0)  # what Lightning's loops do with a batch: a leaf, a LeafSpec
        return [w for w in caught if "LeafSpec" in str(w.message)]


def test_the_leafspec_deprecation_is_silenced_and_other_future_warnings_are_not():
    assert _leafspec_warnings(), "Lightning no longer builds LeafSpec: remove its filter from terminal.py"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        quiet_known_noise()  # in front of "always"
        from lightning.pytorch.utilities._pytree import _tree_flatten

        _tree_flatten(1.0)
        warnings.warn("another deprecation", FutureWarning, stacklevel=1)
    assert [str(w.message) for w in caught] == ["another deprecation"]


def test_the_wandb_logger_leaves_out_the_argument_wandb_warns_about(tmp_path):
    import wandb

    ours = WandbLogger(offline=True, save_dir=str(tmp_path), project="p")
    theirs = LightningWandbLogger(offline=True, save_dir=str(tmp_path), project="p")
    assert "anonymous" in theirs._wandb_init and theirs._wandb_init["anonymous"] is None
    assert "anonymous" not in ours._wandb_init
    assert {k: v for k, v in theirs._wandb_init.items() if k != "anonymous"} == {
        k: v for k, v in ours._wandb_init.items() if k not in ("settings", "mode")
    }
    assert type(ours).__name__ == "WandbLogger"  # the project recognises the logger by its class name
    assert WandbLogger(offline=True, save_dir=str(tmp_path), anonymous=True)._wandb_init["anonymous"] == "allow"
    with mock.patch.object(wandb, "termwarn") as warn:  # wandb as installed warns for None, not for unset
        wandb.Settings(**{k: v for k, v in theirs._wandb_init.items() if k == "anonymous"})
        assert any("anonymous" in str(c) for c in warn.call_args_list)
        warn.reset_mock()
        wandb.Settings()
        assert not any("anonymous" in str(c) for c in warn.call_args_list)


def test_an_offline_wandb_run_ends_with_one_line_instead_of_wandbs_summary(tmp_path, capfd, monkeypatch):
    """A real offline wandb run through the project's logger: wandb's closing sparklines and summary table are
    gone, and one line says where the run is and how to upload it, naming the directory wandb wrote (whether
    wandb's own start lines show depends on how wandb was first set up in the process: not checked). An online
    logger and the user's own settings are left as they are."""
    import wandb

    from image2sphere.training.terminal import finish_loggers

    monkeypatch.delenv("WANDB_SILENT", raising=False)  # as a user runs it
    monkeypatch.delenv("WANDB_QUIET", raising=False)
    monkeypatch.delenv("WANDB_MODE", raising=False)
    wandb.setup()  # wandb set up before the run, as in a notebook: Lightning's WANDB_MODE alone then went online
    logger = WandbLogger(offline=True, save_dir=str(tmp_path), project="p", name="train")
    logger.log_metrics({"test/log_likelihood": 1.5, "epoch": 1})
    finish_loggers([logger])
    err = capfd.readouterr().err
    for gone in ("Run summary", "Run history", "test/log_likelihood", "You can sync this run"):
        assert gone not in err, gone
    (offline,) = (tmp_path / "wandb").glob("offline-run-*")
    assert (
        err.rstrip("\n").splitlines()[-1]
        == f"wandb: offline run saved in {offline}; to upload it: wandb sync {offline}"
    )
    assert any(offline.glob("*.wandb"))  # the run's data: what wandb sync uploads
    assert "settings" not in WandbLogger(offline=False, save_dir=str(tmp_path), project="p")._wandb_init
    own = wandb.Settings(quiet=False)
    assert WandbLogger(offline=True, save_dir=str(tmp_path), settings=own)._wandb_init["settings"] is own


def test_report_prints_and_ends_the_job_log_with_the_text(tmp_path, capsys):
    log_file = tmp_path / "train.log"
    handler = logging.FileHandler(log_file, delay=True)
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        logging.getLogger("image2sphere.x").warning("before")
        report("Test metrics:\n  a  b\nRun directory: /r\n")
    finally:
        root.removeHandler(handler)
        handler.close()
    assert capsys.readouterr().out == "Test metrics:\n  a  b\nRun directory: /r\n\n"
    assert log_file.read_text() == "before\nTest metrics:\n  a  b\nRun directory: /r\n\n"


def test_a_run_prints_only_the_projects_metrics_table_and_its_log_ends_with_it(tiny_run):
    stdout = (tiny_run.parent / "stdout.txt").read_text()
    stderr = (tiny_run.parent / "stderr.txt").read_text()
    assert stdout.count("Test metrics (train") == 1
    assert not re.search(r"Test metric\b", stdout + stderr)  # the header of Lightning's own table
    for noise in ("💡 Tip", "litlogger", "LeafSpec"):
        assert noise not in stdout + stderr, noise
    log = (tiny_run / "train.log").read_text()
    tail = log[log.index("Test metrics (train") :]
    assert tail.rstrip("\n").endswith(f"Run directory: {tiny_run}")
    assert re.search(r"^\s*log lik", tail, re.M | re.I) or "log_likelihood" in tail or "LL" in tail
