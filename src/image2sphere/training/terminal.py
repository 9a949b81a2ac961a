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

**The closing report** (:func:`report`) goes to stdout, as before, and to the file handlers of the
job's log (Hydra's ``<run dir>/<task>.log``), so that the log ends with the metrics and the run
directory as the terminal does.
"""

from __future__ import annotations

import logging
import warnings

from lightning.pytorch.loggers import WandbLogger as _LightningWandbLogger

__all__ = ["WandbLogger", "quiet_known_noise", "report"]

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
