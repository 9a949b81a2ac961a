"""What the terminal of a run shows besides the progress bar: known-harmless messages of the libraries
silenced where they are emitted, and the closing report written to the job's log file too.

**Silenced messages.** :func:`quiet_known_noise` removes three messages that every run printed and that
say nothing about the run. Each filter matches one message of one library, so anything else those
libraries say still shows:

* Lightning (checked with 2.6.6) logs a tip to install ``litlogger`` through its rank-zero logger whenever
  the trainer has no LitLogger (``trainer/connectors/logger_connector/logger_connector.py``);
* Lightning's ``utilities/_pytree.py`` (2.6.6) builds a ``LeafSpec``, which torch 2.13 deprecates with a
  ``FutureWarning`` on every training loop start;
* Lightning's ``WandbLogger`` (2.6.6) always passes ``anonymous=None`` to ``wandb.init``, and wandb (0.31)
  warns that "the anonymous setting has no effect" for any value other than unset: :class:`WandbLogger`
  leaves the argument out when it is ``None`` (``logger.wandb.anonymous=true`` still passes it).

**wandb's closing summary.** At the end of a run wandb (0.31) prints about 25 lines: a sparkline of every
logged value and a second table of the last values, after the project's table, which it pushes off the
screen. An offline run (the default, ``logger.wandb.offline=true``) is therefore started with wandb's
``quiet`` setting, which keeps the lines at the start (where the run is saved) and drops the summary and
the closing advice to upload; :func:`finish_loggers` says that last thing in one line
(:func:`wandb_sync_line`). An online run keeps wandb's output (its link to the run page), and
``+logger.wandb.settings=...`` replaces the setting.

**The closing report** (:func:`report`) goes to stdout, as before, and to the file handlers of the
job's log (Hydra's ``<run dir>/<task>.log``), so that the log ends with the metrics and the run
directory as the terminal does.
"""

from __future__ import annotations

import logging
import sys
import warnings

from lightning.pytorch.loggers import WandbLogger as _LightningWandbLogger

__all__ = ["WandbLogger", "finish_loggers", "quiet_known_noise", "report", "wandb_sync_line"]

# the loggers Lightning's rank_zero_info writes to (the fabric and the pytorch copies of the helper)
_RANK_ZERO_LOGGERS = ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero")
_LITLOGGER_TIP = "💡 Tip: For seamless cloud logging"
_LEAF_DEPRECATION = r"`isinstance\(treespec, LeafSpec\)` is deprecated"


class _DropLitLoggerTip(logging.Filter):
    """Drops Lightning's advertisement for litlogger; every other record passes."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(_LITLOGGER_TIP)


_TIP_FILTER = _DropLitLoggerTip()


def quiet_known_noise() -> None:
    """Install the filters of the module docstring (idempotent; warnings filters are per process, so each
    entry point and each DDP child calls it through :func:`~image2sphere.training.pipeline.train` or
    ``evaluate``)."""
    for name in _RANK_ZERO_LOGGERS:
        logger = logging.getLogger(name)
        if _TIP_FILTER not in logger.filters:
            logger.addFilter(_TIP_FILTER)
    warnings.filterwarnings(
        "ignore", message=_LEAF_DEPRECATION, category=FutureWarning, module=r"lightning\.pytorch\.utilities\._pytree"
    )


class WandbLogger(_LightningWandbLogger):
    """Lightning's :class:`~lightning.pytorch.loggers.WandbLogger` without the ``anonymous=None`` argument
    that makes wandb 0.31 warn on every run (see the module docstring); otherwise the same logger, with
    the same class name (the project recognises it by name)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        if self._wandb_init.get("anonymous") is None:
            self._wandb_init.pop("anonymous", None)
        if self._offline:
            # Lightning (2.6.6) makes a run offline only through the WANDB_MODE variable, which wandb reads
            # once per process: where wandb was set up before (a notebook, an earlier run in the process) the
            # run went online and failed with "No API key configured". The mode is passed to wandb.init.
            self._wandb_init.setdefault("mode", "offline")
            if self._wandb_init.get("settings") is None:
                import wandb

                self._wandb_init["settings"] = wandb.Settings(quiet=True)  # see the module docstring


def wandb_sync_line(run) -> str | None:
    """The closing line of a quiet offline wandb ``run`` (where it is saved, how to upload it); ``None`` for
    another run, whose own output says so."""
    settings = getattr(run, "settings", None)
    offline = getattr(settings, "mode", None) in ("offline", "dryrun")  # wandb 0.31 records offline as dryrun
    if not offline or not getattr(settings, "quiet", False):
        return None
    return f"wandb: offline run saved in {settings.sync_dir}; to upload it: wandb sync {settings.sync_dir}"


def finish_loggers(loggers: list) -> None:
    """Close the run of a wandb logger (the others need nothing), with :func:`wandb_sync_line` after it."""
    for logger in loggers:
        if type(logger).__name__ == "WandbLogger":
            import wandb

            line = wandb_sync_line(wandb.run)
            wandb.finish()
            if line:  # on stderr, where wandb writes its own lines
                print(line, file=sys.stderr, flush=True)


def _job_log_files() -> list[logging.FileHandler]:
    """The file handlers of the root logger (where Hydra's job logging writes ``<task>.log``)."""
    return [h for h in logging.getLogger().handlers if isinstance(h, logging.FileHandler)]


def report(text: str) -> None:
    """Print ``text`` (the closing table and the run directory) and append it, unformatted, to the job's
    log file(s)."""
    print(text)
    for handler in _job_log_files():
        handler.acquire()
        try:
            if handler.stream is None:  # a handler opened lazily (delay=True)
                handler.stream = handler._open()
            handler.stream.write(text + "\n")
            handler.flush()
        finally:
            handler.release()
