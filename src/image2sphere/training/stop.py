"""Stopping a run on a signal: one mechanism for Ctrl-C, SIGTERM and SLURM's requeue signal, on one
process and on every rank of a DDP run.

The rule
--------
* A signal handler only **records** the request (:func:`requested`); it never runs a collective, writes
  a file or raises (except a second Ctrl-C, which stops at once as Python does by default: ``python -m
  src.train`` then ends with one line that says where it stopped and which checkpoint to resume from, and
  exit status 130, :func:`exit_at_once`). A process
  keeps the strongest request it received (the requeue signal over SIGTERM over Ctrl-C), the same order
  in which the ranks combine theirs, so one rank that received two signals decides as two ranks that
  received one each.
* The ranks **decide together** (:func:`decide`) at fixed points that every rank passes the same number
  of times, in the same order: when fitting and when training starts, at the end of every training batch
  (but an epoch's last), at the end of every training epoch, before the recalibration, before the test,
  after every test batch and at the test's end. When any rank was asked, all of them stop at the same
  point: in training after writing ``last.ckpt`` (:class:`~image2sphere.training.checkpoint.EpochCheckpoint`),
  in the test without writing anything.
* **Why the ranks can never wait for each other in a mismatched collective.** The decisions travel on a
  process group of their own (gloo, :class:`_Decisions`), not on the one Lightning and the model use, and
  a thread of each rank runs them. What Lightning synchronises lazily on one rank (rank 0's progress bar
  computes the epoch's synced metrics in its own hook; the other ranks do it later, in the logger's epoch
  end or in the checkpoint callback) therefore never meets a decision: the main group sees the same
  collectives in the same order on every rank whatever callbacks, loggers and progress bars run, and the
  decision group sees one all-reduce per point, which every rank passes equally often. Waiting is
  bounded as well: in training a point only *reads* the decisions of the points before it (``read=
  "earlier"``: by then every rank has passed those, since a training step's gradient all-reduce lies
  between any two of them), and an epoch's end only *sends* (``read="none"``), so that no rank ever
  waits there while another is still inside the lazily synced epoch end. The points that read their own
  decision at once (``read="all"``: before the recalibration, before the test, the test's end) come after
  every collective of the stage before them on every rank. The test gives every rank the same number of
  batches (:class:`~image2sphere.data.loading.ShardSampler` pads the shorter shares with empty slots), so
  its per-batch points match as well. The main group's own order is kept the same on every rank by
  :class:`SyncEpochMetricsFirst`: the epoch's synced metrics are computed by every rank first thing at an
  epoch's end, before any callback's collective (BatchNorm statistics) could meet rank 0's progress bar
  syncing them.
* **Where a stop lands.** A request is acted on at the first point that reads it: after the batch in
  progress, or, when it came in an epoch's last batch, its validation or its end, after the next epoch's
  first batch (its ``last.ckpt`` resumes exactly as any mid-epoch checkpoint; after the last epoch, the
  run stops after training). The validation pass in progress is finished first (a stop in its middle
  would make the resumed run differ from the uninterrupted one).
* **Bounds.** A decision that does not come within the process group's timeout (the DDP strategy's
  ``timeout``, ``trainer.strategy.timeout`` in ``conf/trainer/ddp.yaml``) ends the run with an error that
  names the point this rank waited at (:class:`DecisionTimeout`); every other collective is bounded by the
  same timeout in torch itself. After a signal the process ends within ``grace`` seconds
  (:func:`handle_signals`, ``stop_grace_s`` in the run's config) even when it is stuck where no Python
  code runs (inside a collective that never completes): a watchdog thread learns of the signal from
  Python's wakeup file descriptor, and when no stop has ended the process by then it prints every
  thread's stack and exits with 128 + the signal number.
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
import datetime
import faulthandler
import logging
import os
import queue
import re
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterable, Iterator
from typing import Any, NoReturn

import lightning.pytorch as pl
import torch
from lightning.fabric.plugins.environments import SLURMEnvironment
from lightning.pytorch.trainer.connectors.signal_connector import _SignalConnector

from image2sphere.checks import ConfigError
from image2sphere.training.cluster import is_secondary_rank, slurm_job_id

__all__ = [
    "DEFAULT_GRACE_S",
    "DecisionTimeout",
    "FlagOnlySignalConnector",
    "StopOnRequest",
    "StopRequested",
    "SyncEpochMetricsFirst",
    "TrainingInterrupted",
    "close_decisions",
    "decide",
    "exit_after_stop",
    "exit_at_once",
    "open_decisions",
    "handle_signals",
    "requeue_job",
    "requeue_signals",
    "requested",
    "stopped_at_once",
    "use_flag_only_signals",
]

log = logging.getLogger(__name__)

# A request's weight, in one process and across ranks alike: the requeue signal (save and come back) over
# SIGTERM (save and end) over Ctrl-C.
_PRIORITY = {signal.SIGINT: 1, signal.SIGTERM: 2}
_REQUEUE_PRIORITY = 3
#: seconds after a signal within which the process ends, stopped or not (``stop_grace_s``)
DEFAULT_GRACE_S = 300.0
_READ = ("all", "earlier", "none")


class _Request:
    """What this process was asked (the strongest signal counts), written by the handlers only."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.sigints = 0
        self.requeue_signums: frozenset[int] = frozenset()
        self.previous: dict[int, Any] = {}  # the handlers that were in place before the run's
        self.depth = 0  # nested handle_signals blocks

    def weight(self, signum: int) -> int:
        if signum in self.requeue_signums:
            return _REQUEUE_PRIORITY
        return _PRIORITY.get(signum, _PRIORITY[signal.SIGTERM])

    def record(self, signum: int, _frame: Any) -> None:
        if signum == signal.SIGINT:
            self.sigints += 1
            if self.sigints > 1:
                raise KeyboardInterrupt  # the second Ctrl-C: stop at once
        if self.signum is None or self.weight(signum) > self.weight(self.signum):
            self.signum = int(signum)
        # one line, written with a single system call (no lock that the interrupted code may hold)
        name = signal.Signals(signum).name
        rank = os.environ.get("LOCAL_RANK", "0")
        again = " (Ctrl-C again to stop at once)" if signum == signal.SIGINT else ""
        with contextlib.suppress(OSError):
            os.write(2, f"[rank {rank}] {name} received: stopping at the next safe point{again}\n".encode())

    def code(self) -> int:
        """``priority * 256 + signal number`` (0: nothing asked), what the ranks combine with a maximum."""
        return 0 if self.signum is None else self.weight(self.signum) * 256 + self.signum


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


def _check_grace(grace: float) -> float:
    if isinstance(grace, bool) or not isinstance(grace, int | float) or not grace > 0:
        raise ConfigError(f"stop_grace_s must be a number of seconds > 0, got {grace!r}")
    return float(grace)


@contextlib.contextmanager
def handle_signals(requeue_signals: Iterable[int] = (), grace: float = DEFAULT_GRACE_S) -> Iterator[None]:
    """For the duration of the block, SIGINT, SIGTERM and ``requeue_signals`` only record a request that
    :func:`decide` reads; the previous handlers come back afterwards (a requeue signal's previous handler
    is also what :func:`requeue_job` calls). After the first of these signals the process ends within
    ``grace`` seconds, if need be without a checkpoint (:class:`_Watchdog`), unless the program catches
    the stop's ``SystemExit`` and goes on. A block inside another keeps
    the outer one's request and handlers and adds its own requeue signals for its duration. Outside the
    main thread (where Python allows no handlers) it does nothing."""
    grace = _check_grace(grace)
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    requeue = frozenset(int(s) for s in requeue_signals) - {signal.SIGINT, signal.SIGTERM}
    handled = {signal.SIGINT, signal.SIGTERM, *_REQUEST.requeue_signums} if _REQUEST.depth else set()
    signums = [s for s in (signal.SIGINT, signal.SIGTERM, *sorted(requeue)) if int(s) not in handled]
    previous = {int(s): signal.getsignal(s) for s in signums}
    outer = (_REQUEST.requeue_signums, dict(_REQUEST.previous))
    if not _REQUEST.depth:  # a new run: nothing asked yet
        _REQUEST.signum, _REQUEST.sigints = None, 0
    _REQUEST.requeue_signums = outer[0] | requeue
    _REQUEST.previous = {**previous, **outer[1]}
    _REQUEST.depth += 1
    watchdog = _Watchdog(grace) if _REQUEST.depth == 1 else None
    for s in signums:
        signal.signal(s, _REQUEST.record)
    exiting = False
    try:
        yield
    except (SystemExit, KeyboardInterrupt):  # the process is ending (a stop, a second Ctrl-C)
        exiting = True
        raise
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler if handler is not None else signal.SIG_DFL)
        _REQUEST.depth -= 1
        _REQUEST.requeue_signums, _REQUEST.previous = outer
        if watchdog is not None:  # a process that ends after a signal still ends within the grace
            watchdog.disarm(keep_deadline=exiting and _REQUEST.signum is not None)


class _Watchdog:
    """Ends the process ``grace`` seconds after its first stop signal, wherever its main thread is.

    A Python signal handler runs only when the main thread executes Python code; inside a collective that
    never completes it never runs, and the request is never even recorded. The C-level handler does write
    the signal's number to Python's wakeup file descriptor (:func:`signal.set_wakeup_fd`), which this
    thread reads. From the first of the run's signals on it counts ``grace`` seconds: a stop that the
    ranks decided ends the process long before that (its last batch, its validation, one checkpoint); if
    the process is still alive then, it prints every thread's stack (where this rank was) and exits with
    128 + the signal number. When the block ends by ending the process (``SystemExit``, as a decided stop
    does, or ``KeyboardInterrupt``) after a signal, the deadline stays: the process may still hang on its
    way out (an exit function joining loader workers, a thread that never ends). It then applies to an
    interpreter that is shutting down (its main thread has ended); a program whose main thread still runs at
    the deadline caught the ``SystemExit`` and went on (a test harness, IPython's ``%run``), and is left
    alone. Otherwise the thread ends with the block."""

    def __init__(self, grace: float):
        self.grace = grace
        self.signums = {int(signal.SIGINT), int(signal.SIGTERM)}
        self._read, self._write = os.pipe()
        self._disarm_read, self._disarm_write = os.pipe()
        os.set_blocking(self._write, False)
        try:
            self._previous_fd = signal.set_wakeup_fd(self._write, warn_on_full_buffer=False)
        except ValueError:  # not the main thread of the main interpreter
            self._previous_fd = None
            self._close()
            self._thread = None
            return
        self._thread = threading.Thread(target=self._watch, name="stop-watchdog", daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        first, deadline, kept = None, None, False
        watched = [self._read, self._disarm_read]
        while True:
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            ready, _, _ = select.select(watched, [], [], wait)
            if self._read in ready:
                for number in os.read(self._read, 512):
                    if first is None and (number in self.signums or number in _REQUEST.requeue_signums):
                        first, deadline = number, time.monotonic() + self.grace
            if self._disarm_read in ready:
                keep = os.read(self._disarm_read, 1) == b"k"
                if first is None or not keep:
                    self._close()  # this thread owns the descriptors: nothing reads them after this
                    return
                watched, kept = [self._read], True  # no more signals come here; the deadline stays
            if deadline is not None and time.monotonic() >= deadline:
                if kept and threading.main_thread().is_alive():
                    # The stop's SystemExit left the block long ago and the program still runs: its caller
                    # caught it and went on (a test harness, IPython's %run). Only an interpreter that is
                    # shutting down (its main thread has ended: exit functions, thread joins) is ended.
                    self._close()
                    return
                self._end(first)

    def _end(self, signum: int) -> NoReturn:
        rank = os.environ.get("LOCAL_RANK", "0")
        name = signal.Signals(signum).name
        with contextlib.suppress(OSError):
            os.write(2, (f"[rank {rank}] {name} was received {self.grace:.0f} s ago and the run has not stopped "
                         "(stop_grace_s): it is stuck where no stop can be decided, e.g. in a collective that "
                         "another rank never joins. Ending this process now, without writing a checkpoint; "
                         "where each of its threads was:\n").encode())  # fmt: skip
            faulthandler.dump_traceback(file=2, all_threads=True)
        os._exit(128 + signum)

    def disarm(self, keep_deadline: bool) -> None:
        """The run's handlers are gone: stop reading signals; the thread ends unless a deadline was set and
        ``keep_deadline``."""
        if self._thread is None:
            return
        with contextlib.suppress(ValueError):
            signal.set_wakeup_fd(self._previous_fd if self._previous_fd is not None else -1)
        # the thread ends (and closes the descriptors) unless a deadline is set and kept
        os.write(self._disarm_write, b"k" if keep_deadline else b"x")

    def _close(self) -> None:
        for fd in (self._read, self._write, self._disarm_read, self._disarm_write):
            with contextlib.suppress(OSError):
                os.close(fd)


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


class DecisionTimeout(RuntimeError):
    """The ranks' decision at a point did not come within the process group's timeout: another rank never
    reached that point (it is stuck or it died; its own output says where it was)."""


def exit_after_stop(signum: int, message: str) -> NoReturn:
    """End the process after a stop the ranks decided together (:func:`close_decisions` first): rank 0 logs
    ``message`` (where it stopped, what was kept, how to go on) and exits with 128 + ``signum``; the other
    ranks exit with 0 (a non-zero
    exit of a rank that Lightning started makes it kill the others at once, rank 0 perhaps in the middle
    of a write)."""
    close_decisions()  # every rank stops here alike: the decision still in flight completes on all of them
    if is_secondary_rank():
        raise SystemExit(0)
    log.warning(message)
    raise SystemExit(128 + int(signum))


def stopped_at_once(exc: BaseException) -> bool:
    """Whether ``exc`` ends the run because of a second Ctrl-C: the ``KeyboardInterrupt`` the handler raised,
    or the ``SystemExit(1)`` by which Lightning ends the process after catching it (``trainer.fit``/``test``
    tear down and exit on a ``KeyboardInterrupt``, lightning/pytorch/trainer/call.py)."""
    if _REQUEST.sigints < 2:
        return False
    seen: set[int] = set()
    node: BaseException | None = exc
    while node is not None and id(node) not in seen:  # the exception and the one it was raised while handling
        if isinstance(node, KeyboardInterrupt):
            return True
        if not isinstance(node, SystemExit):
            return False
        seen.add(id(node))
        node = node.__context__
    return False


def exit_at_once(where: str, checkpoint: str | None, resumed_from: str | None,
                 empty_dir: str | None = None) -> NoReturn:  # fmt: skip
    """End the process after a second Ctrl-C (:func:`stopped_at_once`), which stopped it wherever it was without
    saving: one line on stderr, printed last, says where (``where``: ``in epoch 3 (step 120)``), that nothing more
    was saved and which checkpoint to resume from (``checkpoint``: the run's last one, ``None`` when it wrote
    none; ``resumed_from``: the checkpoint the run itself started from); exit status 130 (128 + SIGINT), as a
    shell gives a program that Ctrl-C ended. ``empty_dir``: the run's checkpoint folder, removed when it is
    empty (a write that the second Ctrl-C cut short removes its temporary file). The other ranks of a
    distributed run exit as Lightning has them exit, without a line."""
    if empty_dir is not None:
        with contextlib.suppress(OSError):  # not empty, or already gone: left as it is
            os.rmdir(empty_dir)
    if is_secondary_rank():
        raise SystemExit(1)
    if checkpoint is not None:
        kept = f"the last checkpoint is {checkpoint} (resume with python -m src.train ckpt_path={checkpoint})"
    elif resumed_from is not None:
        kept = (
            f"this run wrote no checkpoint (resume again from {resumed_from}: python -m src.train "
            f"ckpt_path={resumed_from})"
        )
    else:
        kept = "this run wrote no checkpoint"
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    print(f"Stopped at once by a second Ctrl-C {where}: nothing more was saved; {kept}", file=sys.stderr,
          flush=True)  # fmt: skip
    raise SystemExit(128 + int(signal.SIGINT))


# ---------------------------------------------------------------------------------------------- deciding
class _Decisions:
    """The ranks' decisions: one all-reduce (maximum of every rank's request code) per point, on a gloo
    process group of their own, run by a thread of this rank in the order the points were passed.

    :meth:`send` hands this rank's request at a point to the thread and returns at once; :meth:`receive`
    waits for the results of the points sent before (each completes once every rank has sent it), at most
    the group's ``timeout`` for each, and raises :class:`DecisionTimeout` naming the point otherwise."""

    def __init__(self, timeout: datetime.timedelta):
        self.world = torch.distributed.group.WORLD
        self.rank = torch.distributed.get_rank()
        self.timeout = timeout
        self.group = torch.distributed.new_group(backend="gloo", timeout=timeout)
        self._todo: queue.SimpleQueue = queue.SimpleQueue()
        self._done: queue.SimpleQueue = queue.SimpleQueue()
        self._pending: list[str] = []  # the points sent and not received yet, oldest first
        self._thread = threading.Thread(target=self._serve, name="stop-decisions", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while True:
            code = self._todo.get()
            if code is None:
                return
            try:
                value = torch.tensor([code], dtype=torch.int64)
                torch.distributed.all_reduce(value, op=torch.distributed.ReduceOp.MAX, group=self.group)
                self._done.put(int(value.item()))
            except Exception as e:  # noqa: BLE001 - handed to the main thread, which raises it
                self._done.put(e)
                return

    def send(self, code: int, where: str) -> None:
        self._pending.append(where)
        self._todo.put(int(code))

    def receive(self) -> int:
        """The strongest request of every point sent so far (0: none)."""
        strongest = 0
        while self._pending:
            where = self._pending[0]
            seconds = self.timeout.total_seconds()
            try:
                # a Python-level wait: this rank's signal handlers still run meanwhile
                result = self._done.get(timeout=seconds + 10)
            except queue.Empty:
                result = TimeoutError(f"no result within {seconds:.0f} s")
            self._pending.pop(0)
            if isinstance(result, BaseException):
                self._pending.clear()
                raise DecisionTimeout(
                    f"[rank {self.rank}] the ranks' stop decision at {where} did not come within "
                    f"{seconds:.0f} s ({result}): another rank never reached that point; its own output says "
                    "where it was. If a step or a validation pass really takes that long, raise "
                    "trainer.strategy.timeout (conf/trainer/ddp.yaml)"
                ) from result
            strongest = max(strongest, result)
        return strongest

    def close(self) -> None:
        """Receive what is pending (every rank sent it), end the thread and the group."""
        try:
            self.receive()
        finally:
            self._todo.put(None)
            self._thread.join(timeout=10)
            with contextlib.suppress(Exception):
                torch.distributed.destroy_process_group(self.group)


_DECISIONS: _Decisions | None = None


def _distributed() -> bool:
    return (
        torch.distributed.is_available()
        and torch.distributed.is_initialized()
        and torch.distributed.get_world_size() > 1
    )


def open_decisions(trainer: Any = None) -> _Decisions:
    """This process's :class:`_Decisions` for the current process group, made on first use. **Collective**
    the first time (the group's rendezvous): every rank calls it at the same point, before any other rank
    may wait for it in another collective; :meth:`StopOnRequest.setup` does, just after Lightning's
    pre-setup barrier. ``trainer``: where the group's timeout is set (its DDP strategy's ``timeout``)."""
    global _DECISIONS
    if _DECISIONS is None or _DECISIONS.world is not torch.distributed.group.WORLD:
        timeout = getattr(getattr(trainer, "strategy", None), "_timeout", None)  # DDPStrategy(timeout=...)
        if not isinstance(timeout, datetime.timedelta):
            from torch.distributed.constants import default_pg_timeout as timeout
        _DECISIONS = _Decisions(timeout)
    return _DECISIONS


def close_decisions() -> None:
    """End this process's decisions: read the one still in flight (every rank sent it), end the thread and the
    group. Every rank calls it at the same place, before its process ends or its process group is destroyed:
    a process that ends while its thread waits inside gloo for a rank that has already gone aborts
    (measured: "terminate called without an active exception", exit -6, 1 of 66 stops in the test)."""
    global _DECISIONS
    if _DECISIONS is not None:
        decisions, _DECISIONS = _DECISIONS, None
        if torch.distributed.is_initialized() and decisions.world is torch.distributed.group.WORLD:
            decisions.close()


def decide(trainer: Any = None, read: str = "all", where: str = "a decision point") -> int | None:
    """Every rank's request, decided together: the signal that any rank received (the requeue signal
    before SIGTERM before SIGINT), or ``None``. **Collective**: in a distributed run every rank must call
    it at the same points, in the same order, with the same ``read``:

    * ``"all"``: this point's requests included; every rank waits until every other has reached it.
    * ``"earlier"``: the requests of the points before this one (sent there); this point's own request is
      sent and read at the next point. No rank waits for one that has not reached this point yet.
    * ``"none"``: this point's requests are sent and read at the next point; returns ``None``.

    On one process the answer is this process's own request (``None`` for ``"none"``). ``trainer``: where
    the group's timeout is set (its DDP strategy's ``timeout``); ``where``: the point's name in errors."""
    if read not in _READ:
        raise ConfigError(f"read must be one of {', '.join(_READ)}, got {read!r}")
    code = _REQUEST.code()
    if not _distributed():
        return None if read == "none" or not code else code % 256
    decisions = open_decisions(trainer)
    if read == "earlier":
        strongest = decisions.receive()
        decisions.send(code, where)
    else:
        decisions.send(code, where)
        if read == "none":
            return None
        strongest = decisions.receive()
    return strongest % 256 if strongest else None


def decide_or_raise(trainer: Any, where: str, read: str = "all") -> None:
    """:func:`decide`, raising :class:`StopRequested` (naming ``where``) when the ranks stop."""
    signum = decide(trainer, read=read, where=where)
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

    In training: when fitting starts and when training starts (after the sanity check), reading the
    requests of the points before; after every training batch but an epoch's last, reading those of the
    points before; at every training epoch's end, only sending (read at the next epoch's first batch, or
    after training). A stop there writes ``last.ckpt`` through the run's
    :class:`~image2sphere.training.checkpoint.EpochCheckpoint` (when it has one and the run writes
    checkpoints) and raises :class:`TrainingInterrupted`; on the requeue signal rank 0 then asks SLURM to
    requeue the job. In the test: after every test batch (the points before) and at its end (every
    point), raising :class:`StopRequested`. ``python -m src.train`` and ``src.eval`` add it to every
    trainer they build (:func:`use_flag_only_signals`).
    """

    def setup(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        if _distributed():  # every rank, just after Lightning's pre-setup barrier
            open_decisions(trainer)

    def on_fit_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._stop_training(trainer, "when fitting starts", may_save=False)

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._stop_training(trainer, "when training starts", may_save=False)

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:  # fmt: skip
        # after an epoch's last batch the epoch's end sends instead, after its validation: a checkpoint
        # written between the two would resume with the validation and the epoch's end skipped
        if not _last_batch_of_epoch(trainer, batch_idx):
            self._stop_training(trainer, f"after training batch {batch_idx} of epoch {trainer.current_epoch}")

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        # Only sent: Lightning computes the epoch's synced metrics lazily, on rank 0 perhaps already in the
        # progress bar's hook and on the others later; a stop here would write last.ckpt (which reads those
        # metrics) while ranks differ in what they have synced.
        decide(trainer, read="none", where=f"the end of epoch {trainer.current_epoch}")

    def on_test_batch_end(self, trainer: pl.Trainer, *args: Any, **kwargs: Any) -> None:
        decide_or_raise(trainer, "in the test", read="earlier")

    def on_test_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        decide_or_raise(trainer, "in the test", read="all")

    def _stop_training(self, trainer: pl.Trainer, where: str, may_save: bool = True) -> None:
        signum = decide(trainer, read="earlier", where=where)
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


class SyncEpochMetricsFirst(pl.Callback):
    """At a training epoch's end, before any other callback's hook, every rank computes the epoch's logged
    metrics (``trainer.callback_metrics``), which syncs those logged with ``sync_dist=True`` across ranks.

    Lightning computes them lazily, on whichever access comes first: on rank 0 in the progress bar's
    epoch-end hook (it is drawn on rank 0 alone), on the others later, in the checkpoint callback or the
    logger's epoch end. Any collective between the two (BatchNorm statistics recomputed at the epoch's
    end, a user's callback) then met a metric sync on the other rank: measured, a gloo abort ("Received
    data size doesn't match expected size", 64 vs 4 bytes) at the first epoch's end of ``trainer=ddp
    experiment=modelnet10`` with no validation split, and a hang at the stop decision before it. Computed
    here first, on every rank, in the same order, the later accesses find them computed.
    :func:`use_flag_only_signals` puts it first among the trainer's callbacks (Lightning keeps that order
    but for its tuner callbacks, which go first, and checkpoint callbacks, which go last)."""

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        trainer.callback_metrics  # noqa: B018 - computing them is the point


def use_flag_only_signals(trainer: Any) -> None:
    """Switch Lightning's signal handling off for ``trainer`` (see :class:`FlagOnlySignalConnector`), add the
    points where the ranks decide to stop (:class:`StopOnRequest`, last) and have every rank sync the
    epoch's metrics at the same point (:class:`SyncEpochMetricsFirst`, first)."""
    if not isinstance(getattr(trainer, "_signal_connector", None), _SignalConnector):
        raise RuntimeError(
            "this Lightning version has no Trainer._signal_connector: the run's signal handling cannot replace "
            "Lightning's; install a Lightning version within pyproject.toml's range"
        )
    trainer._signal_connector = FlagOnlySignalConnector(trainer)
    if not any(isinstance(c, SyncEpochMetricsFirst) for c in trainer.callbacks):
        trainer.callbacks.insert(0, SyncEpochMetricsFirst())
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
