"""The training progress bar (image2sphere.training.progress, ``callbacks.progress_bar``).

Quick tier, in this process: a tiny Lightning model (4 batches an epoch) fitted with the bar and the
checkpoint callback that ``conf/train.yaml`` composes, its terminal output captured. No ``v_num`` with a
logger; after a resume from a checkpoint written mid-epoch by a SIGTERM (the project's stop,
:mod:`image2sphere.training.stop`) the first training line is ``Epoch 1: ... 2/4`` and the rate counts
from batch 2; ``fast_dev_run`` and a bar switched off (another rank) still work; :func:`batch_progress`
draws inside a test batch, is throttled, and does nothing without a bar. Slow tier: the same resume
through ``python -m src.train`` with every default callback.
"""

from __future__ import annotations

import re
import time
from pathlib import Path

import lightning.pytorch as pl
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from lightning.pytorch.loggers import CSVLogger
from torch import nn
from torch.utils.data import DataLoader, TensorDataset

from conftest import REPO, run_train
from image2sphere import batch_progress as batch_progress_hook
from image2sphere.testing.signal_at import SignalAt
from image2sphere.training import progress, stop
from image2sphere.training.checkpoint import AtomicCheckpointIO, batches_done_in_epoch
from image2sphere.training.progress import EpochProgressBar, batch_progress


class _Tiny(pl.LightningModule):
    """A linear layer; its loss goes to the bar as the real module's does (``prog_bar=True``). ``notes``:
    the :func:`batch_progress` steps each test batch reports."""

    def __init__(self, notes: int = 0):
        super().__init__()
        self.layer = nn.Linear(4, 1)
        self.notes = notes
        self.active_in_training: list = []

    def training_step(self, batch, batch_idx):
        self.active_in_training.append(batch_progress_hook.reporter())
        loss = self.layer(batch[0]).pow(2).mean()
        self.log("train/loss", loss, prog_bar=True, on_step=True, on_epoch=True)
        return loss

    def test_step(self, batch, batch_idx):
        for k in range(1, self.notes + 1):
            batch_progress(k, self.notes, "grid", "chunks")

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


class _BarState(pl.Callback):
    """The training bar's ``(initial, n, description)`` at the end of every training batch."""

    def __init__(self):
        self.seen: list[tuple[int, int, str]] = []

    def on_train_batch_end(self, trainer, *args):
        bar = trainer.progress_bar_callback.train_progress_bar
        self.seen.append((bar.initial, bar.n, bar.desc.removesuffix(": ")))  # set_description appends ": "


def _data() -> DataLoader:
    return DataLoader(TensorDataset(torch.randn(16, 4)), batch_size=4)  # 4 batches an epoch


def _callbacks(tmp_path: Path) -> list[pl.Callback]:
    """``callbacks.progress_bar`` and ``callbacks.model_checkpoint`` as ``conf/train.yaml`` composes them."""
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=[f"callbacks.model_checkpoint.dirpath={tmp_path / 'checkpoints'}"])
    return [instantiate(cfg.callbacks.progress_bar), instantiate(cfg.callbacks.model_checkpoint)]


def _trainer(tmp_path: Path, callbacks: list, **kwargs) -> pl.Trainer:
    options = dict(max_epochs=2, accelerator="cpu", logger=False, enable_model_summary=False,
                   num_sanity_val_steps=0, default_root_dir=tmp_path, plugins=[AtomicCheckpointIO()])  # fmt: skip
    return pl.Trainer(callbacks=callbacks, **{**options, **kwargs})


def _lines(out: str) -> list[str]:
    """The states tqdm drew (it separates them with carriage returns), blank ones left out."""
    return [line.strip() for line in re.split(r"[\r\n]", out) if line.strip()]


# tqdm's line under Lightning's bar format: "Epoch 1:  50%|#####     | 2/4 [00:01<00:01,  1.50it/s, loss=0.1]"
_BAR = re.compile(
    r"(?P<desc>[^:|]+): +\d+%\|[^|]*\| (?P<count>\d+/\S+) \[(?P<clock>[^,\]]+), (?P<rate>[^,\]]+),? ?(?P<postfix>.*)\]$"
)


def _bar(line: str) -> tuple[str, str, str, str]:
    """``(description, count, clock, postfix)`` of a drawn bar (``Epoch 1``, ``2/4``, ``00:00<?``, ``...``),
    whatever glyphs the terminal's encoding gives the bar itself."""
    match = _BAR.match(line)
    assert match, line
    return match["desc"], match["count"], match["clock"], match["postfix"]


def test_default_config_uses_this_bar_and_no_line_shows_v_num(tmp_path, capsys):
    callbacks = _callbacks(tmp_path)
    assert type(callbacks[0]) is EpochProgressBar and callbacks[0].refresh_rate == 10
    # a logger with a version: Lightning's own bar appends v_num=0 to every training line
    trainer = _trainer(tmp_path, callbacks, logger=CSVLogger(tmp_path / "csv"))
    module = _Tiny()
    trainer.fit(module, _data())
    lines = _lines(capsys.readouterr().out)
    assert not [line for line in lines if "v_num" in line]
    # the first line is already the epoch's (Lightning's own first line is "Training: 0/?")
    assert _bar(lines[0])[:2] == ("Epoch 0", "0/4")
    desc, count, _, postfix = _bar(lines[-1])
    assert (desc, count) == ("Epoch 1", "4/4") and "train/loss_step=" in postfix and "train/loss_epoch=" in postfix
    assert module.active_in_training == [None] * 8  # no evaluation bar to note progress on while training


def test_mid_epoch_resume_shows_its_epoch_total_and_batch_and_rates_only_new_batches(tmp_path, capsys):
    callbacks = _callbacks(tmp_path)
    trainer = _trainer(tmp_path, [*callbacks, SignalAt("optimizer_step", occurrence=6)])  # epoch 1, batch 2
    stop.use_flag_only_signals(trainer)
    with stop.handle_signals(), pytest.raises(stop.TrainingInterrupted) as stopped:
        trainer.fit(_Tiny(), _data())
    saved = torch.load(stopped.value.checkpoint, weights_only=True)
    assert saved["epoch"] == 1 and batches_done_in_epoch(saved) == 2
    capsys.readouterr()

    state = _BarState()
    resumed = _trainer(tmp_path, [*_callbacks(tmp_path), state], max_epochs=3)
    resumed.fit(_Tiny(), _data(), ckpt_path=stopped.value.checkpoint)
    bars = [_bar(line) for line in _lines(capsys.readouterr().out)]
    assert bars[0][:3] == ("Epoch 1", "2/4", "00:00<?"), bars[:3]  # no rate before a batch of its own
    epoch_1 = [bar for bar in bars if bar[0] == "Epoch 1"]
    assert epoch_1 == bars[: len(epoch_1)] and epoch_1[-1][1] == "4/4"
    assert [bar[1] for bar in bars[len(epoch_1) :]][:1] == ["0/4"] and bars[-1][:2] == ("Epoch 2", "4/4")
    assert not [bar for bar in bars if "-" in bar[2]]  # no negative rate or time when the next epoch starts
    # tqdm's rate is (n - initial) / elapsed: only batches 3 and 4 count in epoch 1, every batch in epoch 2
    assert state.seen[:2] == [(2, 2, "Epoch 1"), (2, 4, "Epoch 1")]  # refresh_rate 10: drawn again at the end
    assert state.seen[2:] == [(0, 0, "Epoch 2")] * 3 + [(0, 4, "Epoch 2")]


def test_resume_count_follows_the_first_batch_when_the_loop_state_says_otherwise(tmp_path, capsys, monkeypatch):
    """The bar's start read from Lightning's loop state is checked against the first batch's index."""
    callbacks = _callbacks(tmp_path)
    trainer = _trainer(tmp_path, [*callbacks, SignalAt("optimizer_step", occurrence=7)])  # epoch 1, batch 3
    stop.use_flag_only_signals(trainer)
    with stop.handle_signals(), pytest.raises(stop.TrainingInterrupted) as stopped:
        trainer.fit(_Tiny(), _data())
    capsys.readouterr()
    monkeypatch.setattr(progress, "_batches_done_before", lambda trainer: 0)  # as if the state were unreadable
    state = _BarState()
    _trainer(tmp_path, [*_callbacks(tmp_path), state]).fit(_Tiny(), _data(), ckpt_path=stopped.value.checkpoint)
    lines = _lines(capsys.readouterr().out)
    assert [_bar(line)[:3] for line in lines[:2]] == [("Epoch 1", "0/4", "00:00<?"), ("Epoch 1", "3/4", "00:00<?")]
    assert state.seen == [(3, 4, "Epoch 1")]


def test_fast_dev_run_and_a_switched_off_bar(tmp_path, capsys):
    bar = _callbacks(tmp_path)[0]
    _trainer(tmp_path, [bar], fast_dev_run=True).fit(_Tiny(), _data())
    assert _bar(_lines(capsys.readouterr().out)[-1])[:2] == ("Epoch 0", "1/1")
    quiet = _callbacks(tmp_path)[0]
    quiet.disable()  # what Lightning does on every rank but 0
    module = _Tiny(notes=3)
    trainer = _trainer(tmp_path, [quiet], max_epochs=1)
    trainer.fit(module, _data())
    trainer.test(module, _data(), verbose=False)
    assert capsys.readouterr().out == "" and batch_progress_hook.reporter() is None


def test_batch_progress_notes_inside_a_test_batch_are_throttled_and_wiped(tmp_path, capsys):
    bar = EpochProgressBar(refresh_rate=10, batch_progress_interval_s=0)
    _trainer(tmp_path, [bar]).test(_Tiny(notes=3), _data(), verbose=False)
    lines = _lines(capsys.readouterr().out)
    notes = [line for line in lines if "grid" in line]
    assert [_bar(line)[3] for line in notes[:3]] == ["grid 1/3 chunks", "grid 2/3 chunks", "grid 3/3 chunks"]
    assert _bar(lines[-1])[::3] == ("Testing DataLoader 0", "")  # wiped at the batch's end
    assert batch_progress_hook.reporter() is None

    slow = EpochProgressBar(refresh_rate=10)  # 0.5 s between notes: a batch this short shows none
    _trainer(tmp_path, [slow]).test(_Tiny(notes=3), _data(), verbose=False)
    assert "grid" not in capsys.readouterr().out


def test_batch_progress_without_a_bar_does_nothing(capsys):
    assert batch_progress_hook.reporter() is None
    start = time.perf_counter()
    for k in range(100_000):
        batch_progress(k, 100_000, "grid")
    assert time.perf_counter() - start < 1.0  # a global read and a comparison a call
    assert capsys.readouterr() == ("", "")


@pytest.mark.slow
def test_train_command_resumed_mid_epoch_shows_the_epoch_and_batch(tmp_path):
    """``python -m src.train`` with every default callback, stopped by SIGTERM after the second of 3 batches,
    then resumed (about 20 s)."""
    data_dir = tmp_path / "data"
    common = ["logger=csv", "trainer.max_epochs=1", "test=false", "recalibration=off"]
    signal_at = ["+callbacks.signal_at._target_=image2sphere.testing.signal_at.SignalAt",
                 "+callbacks.signal_at.phase=optimizer_step", "+callbacks.signal_at.occurrence=2"]  # fmt: skip
    first = run_train([*common, *signal_at, f"hydra.run.dir={tmp_path / 'first'}"], data_dir, tmp_path, check=False)
    assert first.returncode == 143, first.stderr[-3000:]
    ckpt = tmp_path / "first" / "checkpoints" / "last.ckpt"
    resumed = run_train([*common, f"ckpt_path={ckpt}", f"hydra.run.dir={tmp_path / 'resumed'}"], data_dir, tmp_path)
    bars = [_bar(line) for line in _lines(resumed.stdout) if _BAR.match(line)]
    training = [bar for bar in bars if not bar[0].startswith("Validation")]
    assert training[0][:3] == ("Epoch 0", "2/3", "00:00<?"), training[:3]
    assert training[-1][:2] == ("Epoch 0", "3/3") and "train/loss_epoch=" in training[-1][3]
    assert {bar[0] for bar in training} == {"Epoch 0"} and not [bar for bar in bars if "v_num" in bar[3]]
