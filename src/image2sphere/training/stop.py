"""Stopping a run on a signal: one mechanism for Ctrl-C, SIGTERM and SLURM's requeue signal, on one
process and on every rank of a DDP run.

The rule
--------
* A signal handler only **records** the request (:func:`requested`); it never runs a collective, writes
  a file or raises (except a second Ctrl-C, which stops at once as Python does by default).
* The ranks **decide together** (:func:`decide`, one all-reduce of every rank's request) at fixed points
  that every rank passes the same number of times: when fitting starts (after the process group
  exists), when training starts (after the sanity check), at the end of every training batch (but an
  epoch's last, whose epoch end decides after its validation) and of every training epoch, before the
  recalibration, before the test and after every test batch. When any
  rank was asked, all of them stop at that point: in training after writing ``last.ckpt``
  (:class:`~image2sphere.training.checkpoint.EpochCheckpoint`), in the test without writing anything.
* The validation pass in progress is finished first (a stop in its middle would make the resumed run
  differ from the uninterrupted one); its length bounds how late a stop can come.
* Lightning's own signal handling is switched off (:class:`FlagOnlySignalConnector`): its SIGTERM handler
  broadcasts from inside the handler, wherever the main thread was interrupted (in ``optimizer.step``,
  say), while the other ranks may be in another collective, which deadlocked DDP runs; and each rank
  checked its own flag at points of its own, so one rank could stop while the others waited for it.
* SLURM's requeue signal takes the same path (:func:`requeue_signals`: SIGUSR1 for Lightning's SLURM
  auto-requeue, ``#SBATCH --signal=SIGUSR1@90``; SIGUSR2 for submitit's, ``hydra/launcher=slurm``); after
  ``last.ckpt`` is written the job is requeued (:func:`requeue_job`) and continues from that checkpoint
  in the same directory.

Data-loading workers ignore Ctrl-C and a SIGTERM from outside; they obey only their own rank, which decides
and shuts them down (:func:`image2sphere.data.workers.obey_sigterm_from_parent_only`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import signal
import subprocess
import threading
from collections.abc import Iterable, Iterator
from typing import Any, NoReturn

import lightning.pytorch as pl
import torch
from lightning.fabric.plugins.environments import SLURMEnvironment
from lightning.pytorch.trainer.connectors.signal_connector import _SignalConnector

from image2sphere.training.cluster import is_secondary_rank, slurm_job_id

__all__ = [
    "FlagOnlySignalConnector",
    "StopOnRequest",
    "StopRequested",
    "TrainingInterrupted",
    "decide",
    "exit_after_stop",
    "handle_signals",
    "requeue_job",
    "requeue_signals",
    "requested",
    "use_flag_only_signals",
]

log = logging.getLogger(__name__)

# A request's weight when two ranks were asked for different things: the requeue signal (save and come
# back) wins over SIGTERM (save and end), which wins over Ctrl-C.
_PRIORITY = {signal.SIGINT: 1, signal.SIGTERM: 2}
_REQUEUE_PRIORITY = 3


class _Request:
    """What this process was asked (the first signal counts), written by the handlers only."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.requeue_signums: frozenset[int] = frozenset()
        self.previous: dict[int, Any] = {}  # the handlers that were in place before the run's

    def record(self, signum: int, _frame: Any) -> None:
        if signum == signal.SIGINT and self.signum == signal.SIGINT:
            raise KeyboardInterrupt  # the second Ctrl-C: stop at once
        if self.signum is None:
            self.signum = int(signum)
        # one line, written with a single system call (no lock that the interrupted code may hold)
        name = signal.Signals(signum).name
        rank = os.environ.get("LOCAL_RANK", "0")
        again = " (Ctrl-C again to stop at once)" if signum == signal.SIGINT else ""
        with contextlib.suppress(OSError):
            os.write(2, f"[rank {rank}] {name} received: stopping at the next safe point{again}\n".encode())

    def priority(self) -> int:
        if self.signum is None:
            return 0
        if self.signum in self.requeue_signums:
            return _REQUEUE_PRIORITY
        return _PRIORITY.get(self.signum, _PRIORITY[signal.SIGTERM])


_REQUEST = _Request()


def requested() -> int | None:
    """The signal this process received since :func:`handle_signals` began (``None``: none)."""
    return _REQUEST.signum


def requeue_signals() -> set[int]:
    """The signals on which this process saves and has its SLURM job requeued (read before the run's own
    handlers are installed): Lightning's, SIGUSR1, inside a SLURM job (``SLURMEnvironment``'s default
    ``requeue_signal``, sent by ``#SBATCH --signal=SIGUSR1@90``); and SIGUSR2 where something in this
    process already handles it: submitit, which runs the jobs of ``hydra/launcher=slurm`` and requeues
    them on SIGUSR2 (its handler then runs after ``last.ckpt`` is written, see :func:`requeue_job`)."""
    signums = set()
    if SLURMEnvironment.detect():
        signums.add(int(signal.SIGUSR1))
    if callable(signal.getsignal(signal.SIGUSR2)):
        signums.add(int(signal.SIGUSR2))
    return signums


@contextlib.contextmanager
def handle_signals(requeue_signals: Iterable[int] = ()) -> Iterator[None]:
    """For the duration of the block, SIGINT, SIGTERM and ``requeue_signals`` only record a request that
    :func:`decide` reads; the previous handlers come back afterwards (a requeue signal's previous handler
    is also what :func:`requeue_job` calls). Outside the main thread (where Python allows no handlers) it
    does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    signums = [signal.SIGINT, signal.SIGTERM, *(s for s in requeue_signals if s not in (signal.SIGINT, signal.SIGTERM))]
    previous = {int(s): signal.getsignal(s) for s in signums}
    _REQUEST.signum = None
    _REQUEST.requeue_signums = frozenset(int(s) for s in requeue_signals)
    _REQUEST.previous = previous
    for s in signums:
        signal.signal(s, _REQUEST.record)
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler if handler is not None else signal.SIG_DFL)
        _REQUEST.requeue_signums, _REQUEST.previous = frozenset(), {}


class StopRequested(Exception):
    """The ranks decided to stop outside training (before the recalibration, in the test): nothing is
    written, the run's checkpoint is complete."""

    def __init__(self, signum: int, where: str):
        self.signum, self.where = int(signum), where
        super().__init__(f"stopped by {signal.Signals(self.signum).name} {where}")


class TrainingInterrupted(Exception):
    """The ranks decided to stop in training, after writing ``checkpoint`` (``None`` if none was written:
    before the first batch, or with checkpointing off); ``requeued``: SLURM was asked to requeue the job."""

    def __init__(self, signum: int, checkpoint: str | None, epoch: int, step: int, requeued: bool = False):
        self.signum = int(signum)
        self.checkpoint = checkpoint
        self.epoch = epoch
        self.step = step
        self.requeued = requeued
        name = signal.Signals(self.signum).name
        where = f"checkpoint written to {checkpoint}" if checkpoint else "no checkpoint could be written"
        super().__init__(f"training stopped by {name} in epoch {epoch} at global step {step}; {where}")


def exit_after_stop(signum: int, message: str) -> NoReturn:
    """End the process after a stop the ranks decided together: rank 0 logs ``message`` (where it stopped,
    what was kept, how to go on) and exits with 128 + ``signum``; the other ranks exit with 0 (a non-zero
    exit of a rank that Lightning started makes it kill the others at once, rank 0 perhaps in the middle
    of a write)."""
    if is_secondary_rank():
        raise SystemExit(0)
    log.warning(message)
    raise SystemExit(128 + int(signum))


def decide(trainer: Any = None) -> int | None:
    """Every rank's request, decided together: the signal that any rank received (the requeue signal
    before SIGTERM before SIGINT), or ``None``. **Collective**: in a distributed run every rank must call
    it at the same point. ``trainer``: where the process group and its device are (``None``: the default
    process group, if any, on the CPU or the current CUDA device)."""
    mine = _REQUEST.priority()
    signum = _REQUEST.signum
    distributed = torch.distributed.is_available() and torch.distributed.is_initialized()
    if distributed and torch.distributed.get_world_size() > 1:
        if trainer is not None:
            device = trainer.strategy.root_device
        elif torch.distributed.get_backend() == "nccl":
            device = torch.device("cuda", torch.cuda.current_device())
        else:
            device = torch.device("cpu")
        # [priority, signal number] of the strongest request on any rank
        code = torch.tensor([mine * 256 + (signum or 0)], dtype=torch.int64, device=device)
        torch.distributed.all_reduce(code, op=torch.distributed.ReduceOp.MAX)
        value = int(code.item())
        mine, signum = value // 256, value % 256
    return signum if mine else None


def decide_or_raise(trainer: Any, where: str) -> None:
    """:func:`decide`, raising :class:`StopRequested` (naming ``where``) when the ranks stop."""
    signum = decide(trainer)
    if signum is not None:
        raise StopRequested(signum, where)


class FlagOnlySignalConnector(_SignalConnector):
    """Lightning's signal connector with its handlers switched off: the run's own (:func:`handle_signals`)
    stay in place, Lightning never forwards, broadcasts or saves from inside a handler, and
    ``trainer.received_sigterm`` stays false, so that its loops never stop one rank by themselves."""

    def register_signal_handlers(self) -> None:
        self.received_sigterm = False
        self._original_handlers = {}

    def teardown(self) -> None:
        self._original_handlers = {}


class StopOnRequest(pl.Callback):
    """The points where the ranks decide together whether to stop (the trainer's part of the rule above).

    In training: when fitting starts (the process group exists), when training starts (after the sanity
    check), after every training batch and every training epoch. A stop there writes ``last.ckpt``
    through the run's :class:`~image2sphere.training.checkpoint.EpochCheckpoint` (when it has one and the
    run writes checkpoints) and raises :class:`TrainingInterrupted`; on the requeue signal rank 0 then asks
    SLURM to requeue the job. In the test: after every test batch, raising :class:`StopRequested`.
    ``python -m src.train`` adds it to every trainer it builds (:func:`use_flag_only_signals`).
    """

    def on_fit_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._stop_training(trainer, may_save=False)

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._stop_training(trainer, may_save=False)

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:  # fmt: skip
        # after an epoch's last batch the ranks decide at the epoch's end instead, after its validation: a
        # checkpoint written between the two would resume with the validation and the epoch's end skipped
        if not _last_batch_of_epoch(trainer, batch_idx):
            self._stop_training(trainer)

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._stop_training(trainer)

    def on_test_batch_end(self, trainer: pl.Trainer, *args: Any, **kwargs: Any) -> None:
        decide_or_raise(trainer, "in the test")

    def _stop_training(self, trainer: pl.Trainer, may_save: bool = True) -> None:
        signum = decide(trainer)
        if signum is None:
            return
        path = None
        checkpoint = trainer.checkpoint_callback
        if may_save and checkpoint is not None and hasattr(checkpoint, "save_last_now"):
            path = checkpoint.save_last_now(trainer)  # every rank takes part; rank 0 writes
        requeued = False
        if signum in _REQUEST.requeue_signums and path is not None:
            requeued = requeue_job(signum, trainer)
        raise TrainingInterrupted(signum, path, trainer.current_epoch, trainer.global_step, requeued)


def _last_batch_of_epoch(trainer: pl.Trainer, batch_idx: int) -> bool:
    """Whether ``batch_idx`` is the last training batch of the epoch (the same on every rank)."""
    if trainer.fit_loop.epoch_loop.batch_progress.is_last_batch:
        return True
    total = trainer.num_training_batches
    return isinstance(total, int) and batch_idx + 1 >= total


def use_flag_only_signals(trainer: Any) -> None:
    """Switch Lightning's signal handling off for ``trainer`` (see :class:`FlagOnlySignalConnector`)."""
    if not isinstance(getattr(trainer, "_signal_connector", None), _SignalConnector):
        raise RuntimeError(
            "this Lightning version has no Trainer._signal_connector: the run's signal handling cannot replace "
            "Lightning's; install a Lightning version within pyproject.toml's range"
        )
    trainer._signal_connector = FlagOnlySignalConnector(trainer)
    if not any(isinstance(c, StopOnRequest) for c in trainer.callbacks):
        trainer.callbacks.append(StopOnRequest())


def requeue_job(signum: int, trainer: Any) -> bool:
    """After ``last.ckpt`` was written on a requeue signal: have the SLURM job requeued; ``True`` if asked.

    Where another handler had that signal before the run (submitit's, for ``hydra/launcher=slurm``), it is
    called now, on every rank, in ordinary code instead of in the middle of a step: submitit requeues the
    job from its task 0 and ends that process. Otherwise rank 0 runs ``scontrol requeue <job id>``
    (Lightning's SLURM auto-requeue, unless the trainer's ``SLURMEnvironment`` turns it off)."""
    previous = _REQUEST.previous.get(int(signum))
    if callable(previous) and previous is not _REQUEST.record:
        previous(signum, None)
        return True
    environment = getattr(getattr(trainer, "_accelerator_connector", None), "cluster_environment", None)
    if isinstance(environment, SLURMEnvironment) and not environment.auto_requeue:
        log.info("SLURM auto-requeue is off (SLURMEnvironment(auto_requeue=False)): the job is not requeued")
        return False
    if not trainer.is_global_zero:
        return False
    job = slurm_job_id()
    if job is None or not re.fullmatch(r"[0-9_]+", job):
        log.warning("requeue signal outside a SLURM job (no SLURM_JOB_ID): the job is not requeued")
        return False
    try:
        result = subprocess.run(["scontrol", "requeue", job], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as e:
        log.warning("could not requeue SLURM job %s (%s); resume it by hand from its last.ckpt", job, e)
        return False
    if result.returncode != 0:
        log.warning("scontrol requeue %s failed (%s): %s", job, result.returncode, result.stderr.strip())
        return False
    log.info("Requeued SLURM job %s: it continues from its last.ckpt", job)
    return True
