"""A Lightning callback that sends a signal from inside a chosen moment of a run: how the tests (and the
pre-emption stress check, ``benchmarks/preemption.py``) stop a run exactly where a signal used to hurt.

Given on a command line as ``+callbacks.signal_at._target_=image2sphere.testing.signal_at.SignalAt
+callbacks.signal_at.phase=optimizer_step +callbacks.signal_at.occurrence=3``, or added to a Trainer's
callbacks in a test.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import lightning.pytorch as pl

__all__ = ["PHASES", "SignalAt"]

#: where :class:`SignalAt` can send its signal: setting up (before the first checkpoint), the sanity check,
#: between forward and backward, inside the optimizer's step, a validation batch, inside the write of a
#: checkpoint, an epoch's end, the end of training, a test batch
PHASES = ("fit_start", "sanity_check", "forward_backward", "optimizer_step", "validation", "checkpoint_write",
          "epoch_end", "train_end", "test")  # fmt: skip


class SignalAt(pl.Callback):
    """A Lightning callback that sends ``signal`` from inside ``phase`` (its ``occurrence``-th time on
    ``rank``) to this process (``target="rank"``) or, through a process of its own, to the run's whole
    process group (``"group"``).
    ``stamp``: a file that receives the time it was sent. Given on the command line, e.g.
    ``+callbacks.signal_at._target_=image2sphere.testing.signal_at.SignalAt +callbacks.signal_at.phase=...``.
    """

    def __init__(self, phase: str, occurrence: int = 1, rank: int = 0, target: str = "rank",
                 stamp: str | None = None, signum: int = int(signal.SIGTERM)):  # fmt: skip
        if phase not in PHASES:
            raise ValueError(f"phase must be one of {', '.join(PHASES)}, got {phase!r}")
        if target not in ("rank", "group"):
            raise ValueError(f"target must be rank or group, got {target!r}")
        self.phase, self.occurrence, self.rank, self.target = phase, int(occurrence), int(rank), target
        self.stamp, self.signum, self.seen = stamp, int(signum), 0

    def _tick(self, trainer: Any, phase: str) -> None:
        if phase != self.phase or trainer.global_rank != self.rank:
            return
        self.seen += 1
        if self.seen != self.occurrence:
            return
        if self.stamp:
            Path(self.stamp).write_text(f"{time.time()}\n")
        if self.target == "group":  # sent by another process, as SLURM or kill do; delivered before it returns
            code = "import os, sys; os.killpg(int(sys.argv[1]), int(sys.argv[2]))"
            subprocess.run([sys.executable, "-S", "-c", code, str(os.getpgrp()), str(self.signum)], check=True,
                           start_new_session=True)  # outside the group it signals  # fmt: skip
        else:
            os.kill(os.getpid(), self.signum)

    # the phases
    def setup(self, trainer: Any, pl_module: Any, stage: str) -> None:
        if stage != "fit":
            return
        self._tick(trainer, "fit_start")
        io = trainer.strategy.checkpoint_io
        save = io.save_checkpoint

        def save_and_signal(*args: Any, **kwargs: Any) -> None:
            self._tick(trainer, "checkpoint_write")  # the handler runs here, inside the write
            return save(*args, **kwargs)

        io.save_checkpoint = save_and_signal

    def on_sanity_check_start(self, trainer: Any, pl_module: Any) -> None:
        self._tick(trainer, "sanity_check")

    def on_before_backward(self, trainer: Any, pl_module: Any, loss: Any) -> None:
        self._tick(trainer, "forward_backward")

    def on_train_start(self, trainer: Any, pl_module: Any) -> None:
        for optimizer in trainer.optimizers:  # inside optimizer.step(), before the parameters change
            optimizer.register_step_pre_hook(lambda *_: self._tick(trainer, "optimizer_step"))

    def on_validation_batch_start(self, trainer: Any, *args: Any, **kwargs: Any) -> None:
        if not trainer.sanity_checking:
            self._tick(trainer, "validation")

    def on_train_epoch_end(self, trainer: Any, pl_module: Any) -> None:
        self._tick(trainer, "epoch_end")

    def on_train_end(self, trainer: Any, pl_module: Any) -> None:
        self._tick(trainer, "train_end")

    def on_test_batch_start(self, trainer: Any, *args: Any, **kwargs: Any) -> None:
        self._tick(trainer, "test")
