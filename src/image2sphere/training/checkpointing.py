"""Checkpoints that survive crashes: atomic writes, ``last.ckpt`` after every epoch, graceful Ctrl-C.

* :class:`AtomicCheckpointIO` (a Lightning ``CheckpointIO`` plugin, ``trainer.plugins``) writes every
  checkpoint of the run (``last.ckpt``, top-k files, Lightning's SLURM ``hpc_ckpt_*.ckpt``) to a
  temporary file in the same folder, flushes it to disk and renames it over the old one. A crash or
  a full disk in the middle of a write leaves the previous checkpoint as it was.
* :class:`EpochCheckpoint` is Lightning's ``ModelCheckpoint`` with two promises added: ``last.ckpt``
  is written at the end of every epoch whatever ``save_top_k`` says (Lightning >= 2.5 writes it only
  together with a top-k file), and a first Ctrl-C (SIGINT) or a SIGTERM stops the run at the end of
  the current training batch, after writing ``last.ckpt``; the run then ends with
  :class:`TrainingInterrupted`, which ``python -m src.train`` turns into a line saying how to resume.
  A second Ctrl-C stops at once, as usual. ``trainer.fast_dev_run`` writes no checkpoint.
* A checkpoint written in the middle of an epoch resumes exactly: the data module is told how many
  batches of that epoch were done (:meth:`PoseDataModule.resume_within_epoch
  <image2sphere.data.common.PoseDataModule.resume_within_epoch>`), and its sampler skips them.

SLURM: Lightning's own mechanism applies (``SLURMEnvironment(auto_requeue=True)``, on by default
under SLURM): on the requeue signal (``#SBATCH --signal=SIGUSR1@90``) it writes
``hpc_ckpt_<n>.ckpt`` into the run directory (atomically, through :class:`AtomicCheckpointIO`) and
requeues the job, which finds it again because the run directory of a SLURM job is named after the
job id (``conf/hydra/default.yaml``).
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
from lightning.fabric.utilities.cloud_io import _is_local_file_protocol
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.plugins.io import TorchCheckpointIO
from lightning.pytorch.utilities.exceptions import SIGTERMException

__all__ = ["AtomicCheckpointIO", "EpochCheckpoint", "TrainingInterrupted"]

log = logging.getLogger(__name__)


class TrainingInterrupted(Exception):
    """Training stopped on SIGINT or SIGTERM after writing ``checkpoint`` (``None`` if none could be written)."""

    def __init__(self, signum: int, checkpoint: str | None, epoch: int, step: int):
        self.signum = int(signum)
        self.checkpoint = checkpoint
        self.epoch = epoch
        self.step = step
        name = signal.Signals(self.signum).name
        where = f"checkpoint written to {checkpoint}" if checkpoint else "no checkpoint could be written"
        super().__init__(f"training stopped by {name} in epoch {epoch} at global step {step}; {where}")


class AtomicCheckpointIO(TorchCheckpointIO):
    """Writes a checkpoint to ``<path>.tmp-<pid>``, flushes it to disk, then renames it to ``path``.

    On any failure (a full disk, a quota, a crash) the temporary file is removed and the file that
    was at ``path`` before is untouched; the error names the path. Remote paths (``s3://`` ...) go
    through Lightning's own writer.
    """

    def save_checkpoint(self, checkpoint: dict[str, Any], path, storage_options: Any | None = None) -> None:
        if storage_options is not None or not _is_local_file_protocol(str(path)):
            return super().save_checkpoint(checkpoint, path, storage_options=storage_options)
        import torch

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
        try:
            with open(tmp, "wb") as f:
                torch.save(checkpoint, f)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException as e:
            tmp.unlink(missing_ok=True)
            if isinstance(e, OSError):
                kept = f"the previous {path.name} is intact" if path.exists() else f"no {path.name} was written"
                raise OSError(
                    e.errno,
                    f"could not write checkpoint {path} ({e.strerror or e}); {kept}. Free disk space and resume",
                ) from e
            raise
        _fsync_dir(path.parent)


def _fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable (best effort: not every file system allows it)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class EpochCheckpoint(ModelCheckpoint):
    """``ModelCheckpoint`` that writes ``last.ckpt`` after every epoch and on Ctrl-C / SIGTERM.

    Takes every argument of ``lightning.pytorch.callbacks.ModelCheckpoint`` (``save_last`` must be
    true for the promises above; ``save_top_k``/``monitor`` keep the best epochs as usual).
    """

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self._stop_signal: int | None = None
        self._previous_sigint: Any = None

    # ------------------------------------------------------------------ every epoch
    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        super().on_train_epoch_end(trainer, pl_module)
        if self._may_save(trainer) and self._last_global_step_saved != trainer.global_step:
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))
        self._stop_if_asked(trainer)

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if not trainer.fast_dev_run:  # Lightning's own version writes last.ckpt even then
            super().on_train_end(trainer, pl_module)

    def _may_save(self, trainer: pl.Trainer) -> bool:
        return bool(self.save_last) and not trainer.fast_dev_run and not trainer.sanity_checking

    # ------------------------------------------------------------------ graceful stop
    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._stop_signal = None
        if threading.current_thread() is threading.main_thread():
            self._previous_sigint = signal.getsignal(signal.SIGINT)
            signal.signal(signal.SIGINT, self._on_sigint)

    def _on_sigint(self, signum: int, frame: Any) -> None:
        if self._stop_signal is not None:  # the second Ctrl-C: stop now, as Python does by default
            raise KeyboardInterrupt
        self._stop_signal = signum
        log.warning("Ctrl-C: stopping after this training batch and writing last.ckpt (Ctrl-C again to stop at once)")

    def _restore_sigint(self) -> None:
        if self._previous_sigint is not None and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, self._previous_sigint)
        self._previous_sigint = None

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, *args: Any, **kwargs: Any) -> None:
        super().on_train_batch_end(trainer, pl_module, *args, **kwargs)
        self._stop_if_asked(trainer)

    def _stop_if_asked(self, trainer: pl.Trainer) -> None:
        signum = self._stop_signal
        if signum is None and trainer.received_sigterm:
            signum = signal.SIGTERM
        if trainer.world_size > 1:
            # A signal reaches the ranks of a DDP run at different moments: they decide together, at the
            # end of the same batch, and all stop there when any of them was asked (the checkpoint is
            # written by all of them together).
            if trainer.strategy.reduce_boolean_decision(signum is not None, all=False) and signum is None:
                signum = signal.SIGTERM
        if signum is None:
            return
        path = None
        if self._may_save(trainer):
            if self._last_global_step_saved != trainer.global_step:
                self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))
            path = self.last_model_path or None
        raise TrainingInterrupted(signum, path, trainer.current_epoch, trainer.global_step)

    def on_exception(self, trainer: pl.Trainer, pl_module: pl.LightningModule, exception: BaseException) -> None:
        self._restore_sigint()
        if isinstance(exception, SIGTERMException) and self._may_save(trainer):
            # Lightning's own stop of a DDP run on SIGTERM (rank 0's flag, shared at the start of a batch,
            # all ranks stop together): the batches done so far go into last.ckpt like on our own stop
            if self._last_global_step_saved != trainer.global_step:
                self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))
        super().on_exception(trainer, pl_module, exception)

    def teardown(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        self._restore_sigint()
        super().teardown(trainer, pl_module, stage)

    # ------------------------------------------------------------------ exact resume within an epoch
    def on_load_checkpoint(self, trainer: pl.Trainer, pl_module: pl.LightningModule, checkpoint: dict) -> None:
        super().on_load_checkpoint(trainer, pl_module, checkpoint)
        done = batches_done_in_epoch(checkpoint)
        datamodule = trainer.datamodule
        if done and datamodule is not None and hasattr(datamodule, "resume_within_epoch"):
            epoch = int(checkpoint.get("epoch", 0))
            log.info("resuming epoch %d after its first %d training batches", epoch, done)
            datamodule.resume_within_epoch(epoch, done)


def batches_done_in_epoch(checkpoint: dict) -> int:
    """Training batches of the checkpoint's current epoch that were done (0 for a checkpoint at an epoch's end)."""
    try:
        progress = checkpoint["loops"]["fit_loop"]["epoch_loop.batch_progress"]
        # a checkpoint written at a batch's end has processed that batch but not yet marked it completed
        done = int(progress["current"]["processed"])
    except (KeyError, TypeError, ValueError):
        return 0
    return 0 if progress.get("is_last_batch", True) else done
