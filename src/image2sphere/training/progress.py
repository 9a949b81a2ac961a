"""The training run's terminal progress bar (``callbacks.progress_bar``, ``conf/callbacks/progress_bar.yaml``).

:class:`EpochProgressBar` is Lightning's ``TQDMProgressBar`` (same bars, refresh rate, validation and
test bars, only rank 0 draws in a distributed run) with three things changed, because the stock bar
misled:

* **No** ``v_num``. Lightning appends the logger's version to every training line (``v_num=ak8f`` with
  W&B); it names nothing a user acts on, so only the metrics the module logs with ``prog_bar=True``
  (the loss, the validation metrics) are shown.
* **A resumed epoch is labelled and counted as the epoch it is.** A run resumed from a ``last.ckpt``
  written in the middle of an epoch (Ctrl-C, SIGTERM, SLURM's requeue signal:
  :mod:`image2sphere.training.stop`; the data module skips the batches already done,
  :meth:`~image2sphere.data.datamodule.PoseDataModule.resume_within_epoch`) skips Lightning's
  ``on_train_epoch_start``, where the stock bar gets its label and total, so it read
  ``Training: | 70/? [00:11<00:00, 5.90it/s]``. Here the bar is opened at the epoch the run is in,
  with that epoch's whole number of batches and the count at the batch the run goes on from
  (``Epoch 3:  35%| 70/200``). Speed and time left come only from the batches this process ran: the bar
  starts at ``initial=70``, and tqdm measures its rate from ``n - initial``.
* **Progress inside one long evaluation batch.** :func:`batch_progress` (a module-level function: code
  deep in the model calls it without a trainer) writes ``grid 12/40 chunks`` after the validation, test
  or predict bar of the batch in progress, at most every ``batch_progress_interval_s`` seconds. Outside
  such a batch, on ranks other than 0 and with the bar switched off it returns at once and draws
  nothing.
"""

from __future__ import annotations

import sys
import time
from typing import Any

import lightning.pytorch as pl
from lightning.pytorch.callbacks import TQDMProgressBar
from lightning.pytorch.callbacks.progress.tqdm_progress import Tqdm, convert_inf

from image2sphere import batch_progress as _hook

__all__ = ["EpochProgressBar", "batch_progress"]


def batch_progress(done: int, total: int, what: str, unit: str = "") -> None:
    """Show ``<what> <done>/<total> [<unit>]`` after the bar of the evaluation batch in progress, e.g.
    ``batch_progress(12, 40, "grid", "chunks")`` gives ``grid 12/40 chunks``.

    For work inside one validation, test or predict batch long enough that its bar would seem stuck.
    Without a bar drawing such a batch (training, another rank, the bar switched off, no trainer at all)
    it does nothing. The same as :func:`image2sphere.batch_progress.report`, through which the grid sweeps
    report: the bar of the batch in progress installs itself there (:meth:`EpochProgressBar.batch_progress`)
    and removes itself at the batch's end.
    """
    _hook.report(done, total, what, unit)


class EpochProgressBar(TQDMProgressBar):
    """Lightning's tqdm bar without ``v_num``, labelled and counted right after a mid-epoch resume, and
    with :meth:`batch_progress` for long evaluation batches.

    ``refresh_rate``, ``process_position`` and ``leave`` are ``TQDMProgressBar``'s. ``batch_progress_interval_s``:
    the shortest time between two redraws by :meth:`batch_progress` (an evaluation batch shorter than that
    never shows one).
    """

    def __init__(self, refresh_rate: int = 1, process_position: int = 0, leave: bool = False,
                 batch_progress_interval_s: float = 0.5):  # fmt: skip
        super().__init__(refresh_rate=refresh_rate, process_position=process_position, leave=leave)
        self.batch_progress_interval_s = float(batch_progress_interval_s)
        # batches of the current epoch done by an earlier process (a mid-epoch resume); 0 otherwise
        self._resumed_at = 0
        # the epoch whose start the training bar has seen (on_train_epoch_start), None before the first
        self._bar_epoch: int | None = None
        # the evaluation bar of the batch in progress and what batch_progress last drew on it
        self._batch_bar: Any = None
        self._batch_shown_t = 0.0
        self._batch_note = ""

    # ------------------------------------------------------------------ what the training line shows
    def get_metrics(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> dict[str, Any]:
        """What the module logged with ``prog_bar=True``; Lightning's standard items (the logger's
        ``v_num``) are left out."""
        return dict(trainer.progress_bar_metrics)

    # ------------------------------------------------------------------ the training bar
    def init_train_tqdm(self) -> Tqdm:
        """The training bar, opened at the epoch the run is in: its label, its whole number of batches, and
        the count where this process starts (past the batches done before a mid-epoch resume), so that the
        first line drawn is already right and the rate counts only this process's batches."""
        trainer = self.trainer
        return Tqdm(
            desc=f"Epoch {trainer.current_epoch}",
            total=convert_inf(self.total_train_batches),
            initial=self._resumed_at,
            position=2 * self.process_position,
            disable=self.is_disabled,
            leave=True,
            dynamic_ncols=True,
            file=sys.stdout,
            smoothing=0,
            bar_format=self.BAR_FORMAT,
        )

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._resumed_at = _batches_done_before(trainer)
        self._bar_epoch = trainer.current_epoch if self._resumed_at else None
        super().on_train_start(trainer, pl_module)

    def on_train_epoch_start(self, trainer: pl.Trainer, *args: Any) -> None:
        """The bar moved to the new epoch in one draw. (Lightning's own resets it first, drawing the old
        label at 0 with the old ``initial``: after a resumed epoch that line showed a negative rate.)"""
        self._resumed_at = 0
        self._bar_epoch = trainer.current_epoch
        if self._leave:  # a bar of its own for every epoch, left on the screen
            self.train_progress_bar = self.init_train_tqdm()
        else:
            total = convert_inf(self.total_train_batches)
            _restart(self.train_progress_bar, f"Epoch {trainer.current_epoch}", total, 0)

    def on_train_batch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch: Any,
                             batch_idx: int) -> None:  # fmt: skip
        """A batch of an epoch whose start this bar did not see (a resume in the middle of it, as Lightning
        skips ``on_train_epoch_start`` then), or one the bar's count disagrees with at the first batch of a
        resume: the bar is moved to this epoch and batch, and its clock restarted."""
        super().on_train_batch_start(trainer, pl_module, batch, batch_idx)
        bar = self._train_progress_bar
        if bar is None or bar.disable:
            return
        resumed = self._bar_epoch != trainer.current_epoch
        if resumed or (self._resumed_at and batch_idx != bar.n):
            self._bar_epoch = trainer.current_epoch
            self._resumed_at = batch_idx
            _restart(bar, f"Epoch {trainer.current_epoch}", convert_inf(self.total_train_batches), batch_idx)
        self._resumed_at = 0  # checked once, at the first batch after the resume

    # ------------------------------------------------------------------ progress inside an evaluation batch
    def batch_progress(self, done: int, total: int, what: str, unit: str = "") -> None:
        """Write ``<what> <done>/<total> [<unit>]`` after the bar of the evaluation batch in progress, at
        most every ``batch_progress_interval_s`` seconds (the first time that long after the batch
        started); the last step (``done >= total``) is drawn whenever a step before it was."""
        bar = self._batch_bar
        if bar is None:
            return
        now = time.monotonic()
        last = done >= total and bool(self._batch_note)
        if now - self._batch_shown_t < self.batch_progress_interval_s and not last:
            return
        self._batch_note = f"{what} {done}/{total}" + (f" {unit}" if unit else "")
        self._batch_shown_t = now
        bar.set_postfix_str(self._batch_note, refresh=True)

    def _start_batch(self, bar: Any) -> None:
        if bar is None or bar.disable:
            return
        self._batch_bar, self._batch_shown_t, self._batch_note = bar, time.monotonic(), ""
        _hook.set_reporter(self.batch_progress)  # what batch_progress() and the grid sweeps report to

    def _end_batch(self) -> None:
        """Forget the batch's bar; a note :meth:`batch_progress` drew is wiped, so that it never stands
        next to the next batch's count."""
        bar, self._batch_bar = self._batch_bar, None
        if _hook.reporter() == self.batch_progress:  # this bar's (a bound method equals its twin)
            _hook.set_reporter(None)
        if bar is not None and self._batch_note:
            self._batch_note = ""
            bar.set_postfix_str("", refresh=True)

    def on_validation_batch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch: Any,
                                  batch_idx: int, dataloader_idx: int = 0) -> None:  # fmt: skip
        super().on_validation_batch_start(trainer, pl_module, batch, batch_idx, dataloader_idx)
        self._start_batch(self._val_progress_bar)

    def on_validation_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs: Any, batch: Any,
                                batch_idx: int, dataloader_idx: int = 0) -> None:  # fmt: skip
        self._end_batch()
        super().on_validation_batch_end(trainer, pl_module, outputs, batch, batch_idx, dataloader_idx)

    def on_test_batch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch: Any,
                            batch_idx: int, dataloader_idx: int = 0) -> None:  # fmt: skip
        super().on_test_batch_start(trainer, pl_module, batch, batch_idx, dataloader_idx)
        self._start_batch(self._test_progress_bar)

    def on_test_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs: Any, batch: Any,
                          batch_idx: int, dataloader_idx: int = 0) -> None:  # fmt: skip
        self._end_batch()
        super().on_test_batch_end(trainer, pl_module, outputs, batch, batch_idx, dataloader_idx)

    def on_predict_batch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch: Any,
                               batch_idx: int, dataloader_idx: int = 0) -> None:  # fmt: skip
        super().on_predict_batch_start(trainer, pl_module, batch, batch_idx, dataloader_idx)
        self._start_batch(self._predict_progress_bar)

    def on_predict_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs: Any, batch: Any,
                             batch_idx: int, dataloader_idx: int = 0) -> None:  # fmt: skip
        self._end_batch()
        super().on_predict_batch_end(trainer, pl_module, outputs, batch, batch_idx, dataloader_idx)

    def on_exception(self, trainer: pl.Trainer, pl_module: pl.LightningModule, exception: BaseException) -> None:
        """A batch that raised never reaches its end hook: the hook is cleared here instead."""
        self._end_batch()
        super().on_exception(trainer, pl_module, exception)

    def teardown(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        self._end_batch()
        super().teardown(trainer, pl_module, stage)


def _batches_done_before(trainer: pl.Trainer) -> int:
    """Training batches of the current epoch that an earlier process ran: non-zero only when the run resumes
    from a checkpoint written in the middle of an epoch (read from Lightning's restored loop state; the
    first batch's index confirms it, :meth:`EpochProgressBar.on_train_batch_start`)."""
    fit_loop = trainer.fit_loop
    if not getattr(fit_loop, "restarted_mid_epoch", False):
        return 0
    try:
        return max(0, int(fit_loop.epoch_loop.batch_progress.current.processed))
    except (AttributeError, TypeError, ValueError):
        return 0


def _restart(bar: Any, desc: str, total: int | None, start: int) -> None:
    """Put ``bar`` at ``start`` of ``total`` under ``desc`` with its clock restarted, drawing it once: the
    rate and time left then count only what comes after ``start``."""
    bar.total = total
    bar.initial = bar.n = start
    if bar.disable:  # a disabled tqdm has no clock
        return
    bar.last_print_n = start
    bar.start_t = bar.last_print_t = bar._time()  # what tqdm's reset() does, without drawing a 0 first
    bar.set_description(desc, refresh=True)
