"""Checkpoints: written so that they survive crashes, read back safely, and their model rebuilt.

Writing (``python -m src.train``)
---------------------------------
* :class:`AtomicCheckpointIO` (a Lightning ``CheckpointIO`` plugin, ``trainer.plugins``) writes every
  checkpoint of the run (``last.ckpt``, top-k files, Lightning's SLURM ``hpc_ckpt_*.ckpt``) to a
  temporary file in the same folder, flushes it to disk and renames it over the old one. A crash or
  a full disk in the middle of a write leaves the previous checkpoint as it was.
* :class:`EpochCheckpoint` is Lightning's ``ModelCheckpoint`` with two promises added: ``last.ckpt``
  is written at the end of every epoch whatever ``save_top_k`` says (Lightning >= 2.5 writes it only
  together with a top-k file), and it is written at once when the ranks decide to stop on a signal
  (Ctrl-C, SIGTERM, SLURM's requeue signal: :mod:`image2sphere.training.stop`), after which
  ``python -m src.train`` says how to resume. ``trainer.fast_dev_run`` writes no checkpoint.
* A checkpoint written in the middle of an epoch resumes exactly: the data module is told how many
  batches of that epoch were done (:meth:`PoseDataModule.resume_within_epoch
  <image2sphere.data.datamodule.PoseDataModule.resume_within_epoch>`), and its sampler skips them.

SLURM: on the requeue signal (``SLURMEnvironment(auto_requeue=True)``, on by default under SLURM;
``#SBATCH --signal=SIGUSR1@90``) the run stops like on SIGTERM, writing ``last.ckpt``, and rank 0 asks
SLURM to requeue the job (:mod:`image2sphere.training.stop`); the requeued job finds that checkpoint
because the run directory of a SLURM job is named after the job id (``conf/hydra/default.yaml``,
:mod:`image2sphere.training.cluster`). A ``hpc_ckpt_<n>.ckpt`` that an earlier version left (Lightning's
own requeue checkpoint) is still resumed from.

Reading (``src.eval``, ``src.predict``, resuming)
-------------------------------------------------
A checkpoint (Lightning's ``.ckpt``) holds ``state_dict``, the plain hyperparameters, ``class_names``
and ``run_config``: the resolved Hydra config of the run that wrote it. :func:`load_checkpoint` reads
it with ``torch.load(..., weights_only=True)``: only tensors and plain containers, never arbitrary
pickled code; :func:`build_module` rebuilds its model. Every failure names the file and says what did
not match. The entry points check their ``ckpt_path`` first (:func:`checkpoint_file`): a directory given
instead of a file is refused with the checkpoints found in it as examples (none is picked for the user).
Weights that do not fit the network they are loaded into (:func:`check_weights_fit`: a rebuilt model, or a
resumed run whose command line changed the network's size) are refused in one line that names a few of
the parameters at fault, before Lightning would report every key.
"""

from __future__ import annotations

import logging
import os
import pickle
import re
import zipfile
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import torch
from hydra.utils import instantiate
from lightning.fabric.utilities.cloud_io import _is_local_file_protocol
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.plugins.io import TorchCheckpointIO
from omegaconf import OmegaConf

from image2sphere.checks import ConfigError, InputNotFoundError
from image2sphere.loop_progress import batches_done_in_epoch, epoch_resumed_in
from image2sphere.recalibration import Recalibration

__all__ = [
    "AtomicCheckpointIO",
    "CheckpointError",
    "EpochCheckpoint",
    "batches_done_in_epoch",
    "epoch_resumed_in",
    "build_module",
    "check_resumed_weights",
    "checkpoint_file",
    "checkpoints_in",
    "check_weights_fit",
    "load_checkpoint",
    "weights_mismatch",
]

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------- writing
class AtomicCheckpointIO(TorchCheckpointIO):
    """Writes a checkpoint to ``<path>.tmp-<pid>``, flushes it to disk, then renames it to ``path``.

    On any failure (a full disk, a quota, a crash) the temporary file is removed and the file that
    was at ``path`` before is untouched; the error names the path. Remote paths (``s3://`` ...) go
    through Lightning's own writer.
    """

    def save_checkpoint(self, checkpoint: dict[str, Any], path, storage_options: Any | None = None) -> None:
        if storage_options is not None or not _is_local_file_protocol(str(path)):
            return super().save_checkpoint(checkpoint, path, storage_options=storage_options)
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

    # ------------------------------------------------------------------ every epoch
    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        super().on_train_epoch_end(trainer, pl_module)
        if self._may_save(trainer) and self._last_global_step_saved != trainer.global_step:
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if not trainer.fast_dev_run:  # Lightning's own version writes last.ckpt even then
            super().on_train_end(trainer, pl_module)

    def _may_save(self, trainer: pl.Trainer) -> bool:
        return bool(self.save_last) and not trainer.fast_dev_run and not trainer.sanity_checking

    # ------------------------------------------------------------------ a stop on a signal
    def save_last_now(self, trainer: pl.Trainer) -> str | None:
        """Write ``last.ckpt`` now unless it already holds this step (a stop on a signal, decided by every
        rank together: :class:`~image2sphere.training.stop.StopOnRequest`); its path, or ``None`` when the
        run writes no checkpoints. Every rank calls it; rank 0 writes."""
        if not self._may_save(trainer):
            return None
        if self._last_global_step_saved != trainer.global_step:
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))
        return self.last_model_path or None

    # ------------------------------------------------------------------ exact resume within an epoch
    def on_load_checkpoint(self, trainer: pl.Trainer, pl_module: pl.LightningModule, checkpoint: dict) -> None:
        super().on_load_checkpoint(trainer, pl_module, checkpoint)
        done = batches_done_in_epoch(checkpoint)
        datamodule = trainer.datamodule
        if datamodule is not None and hasattr(datamodule, "start_at_epoch"):
            datamodule.start_at_epoch(epoch_resumed_in(checkpoint))
        if done and datamodule is not None and hasattr(datamodule, "resume_within_epoch"):
            epoch = int(checkpoint.get("epoch", 0))
            log.info("resuming epoch %d after its first %d training batches", epoch, done)
            datamodule.resume_within_epoch(epoch, done)


# ---------------------------------------------------------------------------------------------- reading
class CheckpointError(ConfigError):
    """A checkpoint file that is missing, unreadable, not from this project, or does not fit its model."""


def checkpoint_file(path: str | Path, key: str = "ckpt_path") -> Path:
    """``path`` as a :class:`~pathlib.Path` when it is a file; else :class:`FileNotFoundError` naming ``key``
    (the command line's key): a path that does not exist, or a directory, with the checkpoints found in it
    (:func:`checkpoints_in`) as examples of what to pass. None of them is picked: which one to continue from
    is the user's choice."""
    file = Path(path)
    if file.is_file():
        return file
    if not file.is_dir():
        raise InputNotFoundError(
            f"{key}={path} does not exist; pass the checkpoint of an earlier run, "
            f"e.g. {key}=logs/train/runs/<run>/checkpoints/last.ckpt"
        )
    found = checkpoints_in(file)
    if not found:
        raise InputNotFoundError(
            f"{key}={path} is a directory and holds no checkpoint (*.ckpt in it, in its checkpoints/ or in "
            f"<run>/checkpoints/ below it); pass a checkpoint file, "
            f"e.g. {key}=logs/train/runs/<run>/checkpoints/last.ckpt"
        )
    also = f" (also there: {', '.join(f.relative_to(file).as_posix() for f in found[1:3])})" if len(found) > 1 else ""
    raise InputNotFoundError(f"{key}={path} is a directory; pass a checkpoint file, e.g. {key}={found[0]}{also}")


def checkpoints_in(folder: Path) -> list[Path]:
    """The checkpoint files in ``folder`` or its ``checkpoints/`` (a run directory), else in the ``checkpoints/``
    of the folders in it (a folder of runs): each place's ``last.ckpt`` first, then the newest first."""

    def ordered(files: list[Path]) -> list[Path]:
        def newest_first(f: Path) -> float:
            try:
                return -f.stat().st_mtime
            except OSError:
                return 0.0

        return sorted((f for f in files if f.is_file()), key=lambda f: (f.name != "last.ckpt", newest_first(f)))

    own = ordered([*folder.glob("*.ckpt"), *folder.glob("checkpoints/*.ckpt")])
    return own or ordered(list(folder.glob("*/checkpoints/*.ckpt")))


def load_checkpoint(path: str | Path) -> dict:
    """The contents of a training checkpoint, read with ``weights_only=True`` onto the CPU."""
    path = Path(path)
    if path.is_dir():
        found = checkpoints_in(path)
        example = f", e.g. {found[0]}" if found else ""
        raise CheckpointError(f"{path} is a directory, not a checkpoint file; pass a checkpoint file{example}")
    if not path.is_file():
        raise CheckpointError(
            f"checkpoint not found: {path} (a run writes them to logs/<task>/runs/<run>/checkpoints/last.ckpt)"
        )
    size = path.stat().st_size
    if size == 0:
        raise CheckpointError(
            f"{path} is empty (0 bytes): it was not written completely; use another checkpoint of that run"
        )
    if not zipfile.is_zipfile(path):
        raise CheckpointError(
            f"{path} is not a complete checkpoint ({size:,} bytes that are not the zip archive torch.save writes): "
            "it is truncated (a copy or a save that did not finish) or another kind of file"
        )
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        refused = re.search(r"GLOBAL (\S+)", str(e))
        detail = f" (it names {refused.group(1)})" if refused else ""
        raise CheckpointError(
            f"{path} holds objects other than tensors and plain containers{detail}; such objects are never "
            "loaded, since unpickling them could run code. Checkpoints written by python -m src.train hold none"
        ) from None
    except (RuntimeError, EOFError, OSError, zipfile.BadZipFile, ValueError) as e:
        raise CheckpointError(f"cannot read checkpoint {path}: the file is truncated or corrupt ({e})") from e
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt:
        raise CheckpointError(f"{path} is not a Lightning checkpoint (no 'state_dict')")
    if not isinstance(ckpt.get("run_config"), dict) or "model" not in ckpt["run_config"]:
        raise CheckpointError(
            f"{path} has no 'run_config' with a 'model' section: it was not written by python -m src.train of "
            "this project, so the network it holds cannot be rebuilt"
        )
    _upgrade_run_config(ckpt["run_config"], path)
    return ckpt


def _upgrade_run_config(run_config: dict, path: Path) -> None:
    """Spell out, in a checkpoint's stored config, the settings it was trained with that later
    versions changed the defaults of, so that rebuilding or resuming it keeps its behaviour.

    * ``model.net.projector_normalization`` of I2S: absent before it existed, when the projector
      divided by ``sqrt(n)``; the default is now ``mean``.
    * ``model.net.degree_power`` of the Fourier MLP: absent before it existed, when the last layer's
      outputs were the coefficients as they came (``0``); the default is now ``1``.
    * ``model.net.activation_resolution`` of I2S: absent, the ReLU's grid was 8 whatever lmax was; the
      default (``null``) is now ``lmax + 2``.
    * ``model.net.input_scaling`` of I2S: absent, the encoder saw the ImageNet-normalised images
      (``imagenet``, still the default; spelt out so that the meaning of an old run never follows a
      later default).

    Keys renamed since (:data:`~image2sphere.training.run_config.RENAMED_KEYS`) get their new names:
    ``model.refine_mode`` is ``model.refine``.
    """
    model = run_config.get("model")
    if isinstance(model, dict) and "refine_mode" in model:
        refine = model.pop("refine_mode")
        if refine is not None:
            model["refine"] = refine
    net = (run_config.get("model") or {}).get("net")
    target = str(net.get("_target_", "")) if isinstance(net, dict) else ""
    if target.endswith(".FourierMLP") and "degree_power" not in net:
        net["degree_power"] = 0.0
        log.info("%s predates model.net.degree_power: using 0, the scale it was trained with", path)
    if not target.endswith(".I2S"):
        return
    if "activation_resolution" not in net:
        net["activation_resolution"] = 8
        log.info("%s predates the ReLU grid's band-limit rule: using resolution 8, the grid it was trained with", path)
    if "input_scaling" not in net:
        net["input_scaling"] = "imagenet"
    if net.get("projector", "spatial") == "spatial" and "projector_normalization" not in net:
        net["projector_normalization"] = "sqrt"
        log.info("%s predates model.net.projector_normalization: using 'sqrt', the rule it was trained with", path)


def build_module(ckpt: dict, path: str | Path, **overrides):
    """The :class:`~image2sphere.training.PoseEstimationModule` of a checkpoint, weights loaded.

    ``overrides`` replace entries of the module config (e.g. ``eval_grid_level=5``). The encoder is
    built without downloading pretrained weights (they are in the state dict anyway).
    """
    cfg = OmegaConf.create(ckpt["run_config"]["model"])
    for key, value in overrides.items():
        cfg[key] = value
    if "encoder" in cfg.net and "weights" in cfg.net.encoder:
        cfg.net.encoder.weights = None
    module = instantiate(cfg)
    state = ckpt["state_dict"]
    check_weights_fit(module, state, f"{path} does not fit the model its run_config describes")
    module.load_state_dict(state)
    module.class_names = list(ckpt["class_names"]) if ckpt.get("class_names") else None
    module.run_config = ckpt["run_config"]
    if ckpt.get("recalibration") is not None:
        module.recalibration = Recalibration.from_dict(ckpt["recalibration"], str(path))
    return module.eval()


def weights_mismatch(module: torch.nn.Module, state: dict) -> str | None:
    """How ``state`` (a state dict) fails to fit ``module``: the parameters and buffers that are missing, that are
    not the module's, or that have another shape, a few of each named; ``None`` when it fits."""
    own = module.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    wrong = sorted(k for k in set(own) & set(state) if tuple(own[k].shape) != tuple(state[k].shape))
    parts = []
    for title, keys in (("missing", missing), ("unexpected", unexpected), ("of another shape", wrong)):
        if keys:
            shown = ", ".join(
                f"{k} {tuple(state[k].shape)} vs {tuple(own[k].shape)}" if title == "of another shape" else k
                for k in keys[:5]
            )
            parts.append(f"{len(keys)} parameters {title} ({shown}{', ...' if len(keys) > 5 else ''})")
    return "; ".join(parts) or None


def check_weights_fit(module: torch.nn.Module, state: dict, what: str, advice: str = "") -> None:
    """:class:`CheckpointError` ``"<what>: <the mismatch><advice>"`` when ``state`` does not fit ``module``
    (:func:`weights_mismatch`), before Lightning's own report of every key."""
    mismatch = weights_mismatch(module, state)
    if mismatch is not None:
        raise CheckpointError(f"{what}: {mismatch}{advice}")


def check_resumed_weights(module: torch.nn.Module, ckpt: dict, ckpt_path: str) -> None:
    """Refuse to resume ``ckpt`` into ``module`` (the network a resumed run built: the checkpoint's stored model
    with the command line's changes) when its weights do not fit, naming a few of the parameters at fault."""
    check_weights_fit(
        module,
        ckpt["state_dict"],
        f"ckpt_path={ckpt_path} does not fit the network this command line builds",
        advice="; resume without the model.* overrides that change the network's shape, or leave out ckpt_path "
        "to train a new model",
    )
