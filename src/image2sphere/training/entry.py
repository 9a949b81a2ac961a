"""What the entry points (``src.train``, ``src.eval``, ``src.predict``) do when their job fails.

Each main runs its task inside :func:`entry_point`:

* **A refused value prints one line.** A config value, a path or a dataset that the project's own code
  refuses (:func:`refusal`: a :class:`~image2sphere.checks.Refusal`, also one raised while Hydra
  instantiates a dataset; or a required key such as ``ckpt_path=???`` left out) prints
  ``Error: <message>`` on stderr, and the process exits with status 1. Any other exception (a bug, an
  error of torch or Lightning) keeps Hydra's usual report with its traceback. With
  ``HYDRA_FULL_ERROR=1`` in the environment every exception is re-raised as it is, and Hydra prints the
  full traceback.
* **In a multirun** (``-m``) a refused job does not stop the sweep: its line is logged, the job fails
  as a Hydra job fails (the launcher goes on with the other jobs) and Hydra reports it after the
  batch, with the job's overrides, in two lines (:class:`RefusedStart` is a compact Hydra error).
* **A refused start leaves no run directory.** Hydra creates the job's directory and writes ``.hydra/``
  and the log before the task starts; when the task is refused before anything else was written there
  (:func:`discard_failed_start`), those files and the directory are removed, so that ``src.tables``
  does not list the attempt as an unfinished run. Nothing is removed for any other exception (a bug
  keeps its run directory and log for its report), when the directory holds anything else (a
  checkpoint, a logger's files, ``metrics.json``), once a trainer's loop had started
  (:class:`~image2sphere.training.callbacks.NoteLoopStart`), on the other ranks of a distributed run, in
  a requeued SLURM job, or when the directory existed before this process (an explicit ``hydra.run.dir``
  that was empty: its files are removed and the empty directory is left as it was).

Whether a single run's directory is this process's own is noted by :class:`NoteNewRunDirectory`, a
Hydra callback (``conf/hydra/default.yaml``) called before Hydra creates it. A job of a multirun always
has its own directory (``<sweep dir>/<job number>``), and the sweep directory is new or empty when
the sweep starts (:class:`~image2sphere.training.hydra_callbacks.RefuseExistingOutputDir`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.errors import CompactHydraException, InstantiationException
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue

from image2sphere.checks import Refusal
from image2sphere.training.cluster import is_secondary_rank, is_slurm_requeue

__all__ = [
    "NoteNewRunDirectory",
    "RefusedStart",
    "discard_failed_start",
    "entry_point",
    "loop_started",
    "note_loop_start",
    "refusal",
]

log = logging.getLogger(__name__)
# what Hydra writes into a job's directory before the task starts (besides the log)
HYDRA_FILES = ("config.yaml", "hydra.yaml", "overrides.yaml")
# written by src.train before its data is read, in a run that resumes a checkpoint
EARLY_FILES = ("resumed_config.yaml",)

# single-run directories that did not exist before this process's Hydra created them (absolute paths)
_NEW_RUN_DIRS: set[str] = set()


class RefusedStart(CompactHydraException):
    """A multirun job's refusal, as Hydra reports a failed job: its message only, no traceback."""


class NoteNewRunDirectory(Callback):
    """Notes, before Hydra creates it, whether a single run's directory (``hydra.run.dir``) is new: only a
    directory that this process made is ever removed by :func:`discard_failed_start`."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        if is_secondary_rank():
            return
        HydraConfig.instance().set_config(config)  # lets ${hydra:...} in the directory resolve
        path = os.path.abspath(str(OmegaConf.select(config, "hydra.run.dir")))
        if not os.path.lexists(path):
            _NEW_RUN_DIRS.add(path)


def _multirun() -> bool:
    """Whether this is a job of a Hydra multirun (``-m``)."""
    from hydra.types import RunMode

    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def _full_error_requested() -> bool:
    return os.environ.get("HYDRA_FULL_ERROR") == "1"  # what Hydra itself checks


# whether a trainer of this process has started a loop (sanity check, training, validation, test,
# prediction) since the entry point's task began: set by NoteLoopStart, read by discard_failed_start
_LOOP: dict[str, bool] = {"started": False}


def note_loop_start() -> None:
    """Record that a trainer's loop has started: the job's work began, its directory is kept whatever happens
    next (:class:`~image2sphere.training.callbacks.NoteLoopStart` calls this)."""
    _LOOP["started"] = True


def loop_started() -> bool:
    """Whether a trainer's loop has started in this entry point's task."""
    return _LOOP["started"]


def refusal(exc: BaseException) -> str | None:
    """The one-line message of ``exc`` if it refuses the user's input, else ``None`` (it keeps its traceback).

    A refusal is a :class:`~image2sphere.checks.Refusal` (a config value, a missing input, an output that
    would be overwritten; the project's code raises nothing else for a user's input), also when it was
    raised while Hydra instantiated a config node (a data module that finds no dataset), or a required
    config value (``???``) that was not given.
    """
    if isinstance(exc, InstantiationException) and exc.__cause__ is not None:
        exc = exc.__cause__
    if isinstance(exc, MissingMandatoryValue):
        key = getattr(exc, "full_key", None) or "a required key"
        return f"{key} is required: give it on the command line ({key}=...)"
    return str(exc) if isinstance(exc, Refusal) else None


def _job_log_handlers(directory: Path) -> list[tuple[logging.Logger, logging.FileHandler]]:
    """The file handlers (Hydra's job log) that write into ``directory``, with their loggers."""
    loggers = [logging.getLogger()] + [
        lg for lg in logging.Logger.manager.loggerDict.values() if isinstance(lg, logging.Logger)
    ]
    out = []
    for lg in loggers:
        for handler in lg.handlers:
            if isinstance(handler, logging.FileHandler) and Path(handler.baseFilename).parent == directory:
                out.append((lg, handler))
    return out


def discard_failed_start(exc: BaseException) -> bool:
    """Remove the directory of this Hydra job when its task was refused (:func:`refusal`) before writing
    anything.

    Removed: Hydra's ``.hydra/{config,hydra,overrides}.yaml``, the job's log (the file handlers that write
    into the directory) and ``resumed_config.yaml``, then the directory itself when it is empty and this
    process made it (a single run noted by :class:`NoteNewRunDirectory`, or a job of a multirun). Nothing
    is removed for an exception that is no refusal, when the directory holds any other file or folder,
    once a loop had started (:func:`loop_started`), on a secondary rank or in a requeued SLURM job.
    Returns whether the directory is gone."""
    if refusal(exc) is None or loop_started():
        return False
    if not HydraConfig.initialized() or is_secondary_rank():
        return False
    hc = HydraConfig.get()
    directory = Path(os.path.abspath(str(hc.runtime.output_dir)))
    if not directory.is_dir() or is_slurm_requeue(directory):
        return False
    handlers = _job_log_handlers(directory)
    hydra_dir = directory / str(hc.output_subdir) if hc.output_subdir is not None else None
    ours = {directory / name for name in EARLY_FILES} | {Path(h.baseFilename) for _, h in handlers}
    if hydra_dir is not None:
        ours |= {hydra_dir / name for name in HYDRA_FILES}
    for entry in directory.iterdir():
        if entry == hydra_dir and entry.is_dir() and not entry.is_symlink():
            if any(f not in ours or not f.is_file() or f.is_symlink() for f in entry.iterdir()):
                return False
        elif entry not in ours or not entry.is_file() or entry.is_symlink():
            return False  # something else was written there: leave the directory as it is
    for lg, handler in handlers:
        lg.removeHandler(handler)
        handler.close()
    try:
        for path in sorted(ours):
            if path.is_file():
                path.unlink()
        if hydra_dir is not None and hydra_dir.is_dir():
            hydra_dir.rmdir()
        if _multirun() or str(directory) in _NEW_RUN_DIRS:  # this process made it
            directory.rmdir()
            _NEW_RUN_DIRS.discard(str(directory))
            return True
    except OSError as e:  # another process wrote there meanwhile, or no permission: leave the rest
        log.debug("could not remove the directory of the failed start %s: %s", directory, e)
    return False


LIGHTNING_LOGGERS = ("lightning.pytorch", "lightning.fabric")


def lightning_logs_on_their_own() -> None:
    """Lightning's loggers print to the console through a handler of their own and not through the root
    logger's, whatever the order of imports. Lightning (2.6) decides this when it is imported: with no handler
    on the root logger it gives ``lightning.pytorch`` and ``lightning.fabric`` a console handler and stops
    them from propagating; imported after Hydra has configured the root logger (the entry points import it
    when a run starts) they propagate, and every message reaches the terminal twice (Hydra's console
    handler and the ``lightning`` logger's ``INFO:`` one) and the job's log file. This sets the first
    arrangement, which runs have always shown."""
    for name in LIGHTNING_LOGGERS:
        logger = logging.getLogger(name)
        if not logger.handlers:
            logger.addHandler(logging.StreamHandler())
        logger.setLevel(logging.INFO)
        logger.propagate = False


@contextlib.contextmanager
def entry_point() -> Iterator[None]:
    """Run an entry point's task: a refused value prints one line and exits with status 1 (a failed job in a
    multirun), and a start that failed before writing anything leaves no directory (see the module docstring).
    Lightning's messages keep their own console line (:func:`lightning_logs_on_their_own`)."""
    lightning_logs_on_their_own()
    _LOOP["started"] = False  # a new task (a job of a multirun runs in the same process as the one before)
    try:
        yield
    except Exception as exc:
        discard_failed_start(exc)
        message = refusal(exc)
        if message is None or _full_error_requested():
            raise
        line = f"Error: {message}"
        if _multirun():  # fail this job only: the launcher goes on with the others and Hydra reports it
            log.error(line)
            raise RefusedStart(line) from exc
        print(line, file=sys.stderr)
        raise SystemExit(1) from None
