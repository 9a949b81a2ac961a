"""Loading the checkpoints written by ``python -m src.train`` safely, and rebuilding their model.

A checkpoint (Lightning's ``.ckpt``) holds ``state_dict``, the plain hyperparameters, ``class_names``
and ``run_config``: the resolved Hydra config of the run that wrote it. It is read with
``torch.load(..., weights_only=True)``: only tensors and plain containers, never arbitrary pickled
code. Every failure names the file and says what did not match.
"""

from __future__ import annotations

import logging
import pickle
import re
import zipfile
from pathlib import Path

import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

__all__ = ["CheckpointError", "build_module", "load_checkpoint"]

log = logging.getLogger(__name__)


class CheckpointError(ValueError):
    """A checkpoint file that is missing, unreadable, not from this project, or does not fit its model."""


def load_checkpoint(path: str | Path) -> dict:
    """The contents of a training checkpoint, read with ``weights_only=True`` onto the CPU."""
    path = Path(path)
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
    """
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
    own = module.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    wrong = sorted(k for k in set(own) & set(state) if own[k].shape != state[k].shape)
    if missing or unexpected or wrong:
        parts = []
        for title, keys in (("missing", missing), ("unexpected", unexpected), ("of another shape", wrong)):
            if keys:
                shown = ", ".join(
                    f"{k} {tuple(state[k].shape)} vs {tuple(own[k].shape)}" if title == "of another shape" else k
                    for k in keys[:5]
                )
                parts.append(f"{len(keys)} parameters {title} ({shown}{', ...' if len(keys) > 5 else ''})")
        raise CheckpointError(f"{path} does not fit the model its run_config describes: " + "; ".join(parts))
    module.load_state_dict(state)
    module.class_names = list(ckpt["class_names"]) if ckpt.get("class_names") else None
    module.run_config = ckpt["run_config"]
    return module.eval()
