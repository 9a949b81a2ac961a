"""The LightningModule that trains and evaluates any pose network with an SO(3) Fourier output.

Conventions
-----------
* The network maps ``images (B, 3, H, W)`` (and ``class_index (B,)`` when it was built with
  ``num_classes > 0``) to coefficients ``(B, n_so3_coeffs(lmax))`` in the flat Wigner layout; it
  exposes ``lmax`` (:class:`image2sphere.nn.I2S`, :class:`image2sphere.nn.FourierMLP`).
* Training loss: cross-entropy of the grid softmax at ``train_grid_level`` against the grid point
  nearest the label, ``logsumexp_i f(R_i) - f(R_label)``, evaluated with the fast grid evaluator
  (no ``(B, N)`` tensor).
* Batches are dicts (:mod:`image2sphere.data`): ``image``, ``class_index``, and either
  ``rotation (B, 3, 3)`` (training) or ``rotations (B, M, 3, 3)`` with ``mask (B, M)`` (evaluation),
  optionally ``skipped``: corrupt images dropped from the batch (``dataset.on_corrupt=skip``). They are
  counted (``<stage>/skipped_images``, and ``skipped_images`` in the test metrics); a batch whose images
  were all skipped is ``None`` and is passed over.
* Metrics follow docs/evaluation.md (:mod:`image2sphere.metrics`): validation at ``val_grid_level``,
  test at ``eval_grid_level`` (spread at ``spread_grid_level``). The final test metrics are kept in
  :attr:`test_metrics` and logged as ``test/<metric>[/<class>]``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import lightning.pytorch as pl
import numpy as np
import torch
from torch import nn

from image2sphere.data.common import stable_seed
from image2sphere.metrics import (
    check_targets,
    log_likelihood_pairs,
    min_angular_error_deg,
    spread_deg,
    summarize_pose_metrics,
)
from image2sphere.so3.distribution import LOG_UNIFORM_DENSITY, SO3Distribution
from image2sphere.so3.grid import (
    MAX_DENSE_LEVEL,
    MAX_STREAMED_LEVEL,
    check_level,
    so3_grid_size,
    so3_healpix_index_to_matrix,
    so3_healpix_nearest_index,
)
from image2sphere.so3.grid_eval import get_grid_evaluator

__all__ = ["NonFiniteLossError", "PoseEstimationModule"]


class NonFiniteLossError(FloatingPointError):
    """Raised when the training loss becomes NaN or infinite (the run stops before that step is taken or saved)."""


class PoseEstimationModule(pl.LightningModule):
    """Cross-entropy training on an SO(3) grid and the evaluation of docs/evaluation.md.

    Args:
        net: the pose network (built by Hydra from ``model.net``).
        optimizer: a partial optimizer, called with the parameters (``_partial_: true`` in config).
        scheduler: an optional partial learning-rate scheduler, called with the optimizer.
        scheduler_interval: ``"epoch"`` or ``"step"``.
        train_grid_level: grid of the training loss (3 in the paper).
        val_grid_level: grid of the validation metrics.
        eval_grid_level: grid of the test metrics (5 in the paper).
        spread_grid_level: grid of the spread metric (a full-grid sum over all ground truths).
        class_names: names of the classes (``class_index`` values); set by the training script from
            the data module when ``None``.
        refine_mode: refine the test point estimate by gradient ascent on the Fourier series.
    """

    def __init__(
        self,
        net: nn.Module,
        optimizer: Callable[..., torch.optim.Optimizer],
        scheduler: Callable[..., torch.optim.lr_scheduler.LRScheduler] | None = None,
        scheduler_interval: str = "epoch",
        train_grid_level: int = 3,
        val_grid_level: int = 3,
        eval_grid_level: int = 5,
        spread_grid_level: int = 4,
        class_names: Sequence[str] | None = None,
        refine_mode: bool = False,
    ):
        super().__init__()
        if not hasattr(net, "lmax"):
            raise ValueError(f"model.net must expose its band limit as .lmax; {type(net).__name__} does not")
        if scheduler_interval not in ("epoch", "step"):
            raise ValueError(f"model.scheduler_interval must be 'epoch' or 'step', got {scheduler_interval!r}")
        self.check_grid_levels(
            train_grid_level=train_grid_level,
            val_grid_level=val_grid_level,
            eval_grid_level=eval_grid_level,
            spread_grid_level=spread_grid_level,
        )
        # Only plain values go into checkpoints (they must load with torch.load(weights_only=True));
        # the full resolved config is stored separately as ``run_config``.
        self.save_hyperparameters(logger=False, ignore=["net", "optimizer", "scheduler"])
        self.optimizer_factory = optimizer
        self.scheduler_factory = scheduler
        self.net = net
        self.lmax = net.lmax
        self.class_names = list(class_names) if class_names is not None else None
        self.test_metrics: dict[str, float] = {}
        self.skipped_images: dict[str, int] = {}
        self._records: dict[str, list[torch.Tensor]] = {}
        self._seed_base = torch.initial_seed()
        self.run_config: dict | None = None  # the resolved Hydra config, stored in checkpoints

    @staticmethod
    def check_grid_levels(prefix: str = "model.", **levels: int) -> None:
        """Refuse grid levels this module cannot evaluate on, naming the key (streamed work up to level 7, the
        spread's dense grid up to level 6).

        Called by the constructor and, before any data is read or rendered, by the training run's
        config check (:func:`image2sphere.training.run_config.check_train_config`).
        """
        for key, level in levels.items():
            if key.endswith("spread_grid_level"):  # the spread sums one value per grid point
                check_level(level, name=f"{prefix}{key}", max_level=MAX_DENSE_LEVEL, purpose="the spread's dense grid")
            else:
                check_level(level, name=f"{prefix}{key}", max_level=MAX_STREAMED_LEVEL, purpose="streamed evaluation")

    # ------------------------------------------------------------------ forward
    def forward(self, images: torch.Tensor, class_index: torch.Tensor | None = None) -> torch.Tensor:
        if getattr(self.net, "num_classes", 0):
            return self.net(images, class_index)
        return self.net(images)

    def _evaluator(self, level: int, coeffs: torch.Tensor):
        return get_grid_evaluator(self.lmax, level, coeffs.dtype, coeffs.device)

    def _nll(self, coeffs: torch.Tensor, rotation: torch.Tensor, level: int) -> torch.Tensor:
        """Per-image cross-entropy ``(B,)`` against the grid point nearest ``rotation (B, 3, 3)``."""
        ev = self._evaluator(level, coeffs)
        index = so3_healpix_nearest_index(rotation.detach(), level).to(coeffs.device)  # [B]
        return ev.logsumexp(coeffs) - ev.logits_at(coeffs, index[:, None])[:, 0]

    def _count_skipped(self, batch: dict | None, stage: str) -> bool:
        """Count the corrupt images left out of ``batch``; False when nothing is left of it."""
        if batch is None:
            # all images of the batch were skipped; their number is unknown here, count at least one
            self.skipped_images[stage] = self.skipped_images.get(stage, 0) + 1
            return False
        skipped = int(batch.get("skipped", 0))
        if skipped:
            self.skipped_images[stage] = self.skipped_images.get(stage, 0) + skipped
        return True

    # ------------------------------------------------------------------ training
    def training_step(self, batch: dict | None, batch_idx: int) -> torch.Tensor | None:
        if not self._count_skipped(batch, "train"):
            return None
        coeffs = self(batch["image"], batch.get("class_index"))
        loss = self._nll(coeffs, batch["rotation"], self.hparams.train_grid_level).mean()
        if not torch.isfinite(loss):
            raise NonFiniteLossError(
                f"training loss is {loss.item()} at epoch {self.current_epoch}, batch {batch_idx} "
                f"(global step {self.global_step}); the run was stopped before this step could reach a "
                "checkpoint. Lower model.optimizer.lr or check the data"
            )
        self.log("train/loss", loss, prog_bar=True, on_step=True, on_epoch=True, batch_size=len(coeffs))
        return loss

    # ------------------------------------------------------------------ evaluation
    def _evaluate(self, batch: dict, level: int, spread_level: int | None) -> dict[str, torch.Tensor]:
        coeffs = self(batch["image"], batch.get("class_index"))
        targets, mask = batch["rotations"], batch["mask"]
        mask = check_targets(targets, mask, len(coeffs))
        ev = self._evaluator(level, coeffs)
        lse, _, argmax = ev.logsumexp_and_max(coeffs)  # [B], [B], [B]
        dist = SO3Distribution(coeffs, self.lmax)
        if self.hparams.refine_mode:
            pred = dist.mode(level, refine=True).to(targets.dtype)
        else:
            pred = so3_healpix_index_to_matrix(argmax, level, dtype=targets.dtype).to(targets.device)
        ll = log_likelihood_pairs(dist, targets, mask, level, log_normalizer=lse)  # [B, M], NaN on padding
        log_n = math.log(math.prod(so3_grid_size(level)))
        out = {
            "class_index": batch["class_index"],
            "index": batch.get("index", torch.full_like(batch["class_index"], -1)),
            "error_deg": min_angular_error_deg(pred, targets, mask),
            "ll_sum": ll.masked_fill(~mask, 0.0).sum(1),
            "ll_count": mask.sum(1),
            # -log p at the grid point nearest the rendering rotation (the loss, at this level)
            "nll_first": log_n + LOG_UNIFORM_DENSITY - ll[:, 0],
        }
        if spread_level is not None:
            out["spread"] = spread_deg(dist, targets, mask, spread_level)
        return out

    def _record(self, out: dict[str, torch.Tensor]) -> None:
        for key, value in out.items():
            self._records.setdefault(key, []).append(value.detach().cpu())

    def _summarize(self) -> dict[str, float]:
        records = {k: torch.cat(v) for k, v in self._records.items()}
        self._records = {}
        records = self._gather(records)
        names = self.class_names or [str(c) for c in range(int(records["class_index"].max()) + 1)]
        metrics = summarize_pose_metrics(
            records["class_index"],
            names,
            error_deg=records["error_deg"],
            ll_sum=records["ll_sum"],
            ll_count=records["ll_count"],
            spread=records.get("spread"),
        )
        metrics["loss"] = float(records["nll_first"].double().mean())
        return metrics

    def _gather(self, records: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Records of all processes, each image once (distributed samplers pad with repeats)."""
        trainer = self._trainer
        if trainer is None or trainer.world_size == 1 or not torch.distributed.is_initialized():
            return records
        gathered: list = [None] * trainer.world_size
        torch.distributed.all_gather_object(gathered, records)
        merged = {k: torch.cat([g[k] for g in gathered]) for k in records}
        key = merged["class_index"].long() * (int(merged["index"].max()) + 2) + merged["index"].long()
        _, first = np.unique(key.numpy(), return_index=True)
        first = torch.from_numpy(np.sort(first))
        return {k: v[first] for k, v in merged.items()}

    def on_train_epoch_end(self) -> None:
        if self.skipped_images.get("train"):
            self.log("train/skipped_images", float(self.skipped_images["train"]))

    def validation_step(self, batch: dict | None, batch_idx: int) -> None:
        if self._count_skipped(batch, "val"):
            self._record(self._evaluate(batch, self.hparams.val_grid_level, None))

    def on_validation_epoch_end(self) -> None:
        if not self._records:
            return
        m = self._summarize()
        self.log_dict(
            {
                "val/loss": m["loss"],
                "val/log_likelihood": m["log_likelihood"],
                "val/median_error_deg": m["median_error_deg"],
                "val/acc15": m["acc15"],
            },
            prog_bar=True,
            sync_dist=False,
        )

    def test_step(self, batch: dict | None, batch_idx: int) -> None:
        if self._count_skipped(batch, "test"):
            self._record(self._evaluate(batch, self.hparams.eval_grid_level, self.hparams.spread_grid_level))

    def on_test_epoch_start(self) -> None:
        self.skipped_images.pop("test", None)

    def on_test_epoch_end(self) -> None:
        self.test_metrics = self._summarize()
        if self.skipped_images.get("test"):
            # the metrics do not cover every test image: say so next to them
            self.test_metrics["skipped_images"] = float(self.skipped_images["test"])
        self.log_dict({f"test/{k}": v for k, v in self.test_metrics.items()}, sync_dist=False)

    # ------------------------------------------------------------------ optimisation
    def configure_optimizers(self):
        optimizer = self.optimizer_factory(params=self.trainer.model.parameters())
        if self.scheduler_factory is None:
            return {"optimizer": optimizer}
        scheduler = self.scheduler_factory(optimizer=optimizer)
        return {
            "optimizer": optimizer,
            "lr_scheduler": {"scheduler": scheduler, "interval": self.hparams.scheduler_interval, "frequency": 1},
        }

    # ------------------------------------------------------------------ checkpoints
    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["class_names"] = self.class_names
        if self.run_config is not None:
            checkpoint["run_config"] = self.run_config

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        if checkpoint.get("class_names") is not None:
            self.class_names = list(checkpoint["class_names"])

    # ------------------------------------------------------------------ exact resume
    def on_fit_start(self) -> None:
        self._seed_base = torch.initial_seed()  # the run's seed (seed_everything), before any reseeding

    def on_train_batch_start(self, batch: dict, batch_idx: int) -> None:
        # The network's own randomness (the projector's random grid subset) comes from torch's global
        # generator. Reseeding it from (seed, global step) before every step makes each step's draws
        # independent of everything before it, so a run resumed from a checkpoint, one written at an
        # epoch's end or in the middle of an epoch, continues exactly as the uninterrupted run (the data
        # order and labels follow the same rule, see image2sphere.training.checkpointing).
        torch.manual_seed(stable_seed("train-step", self._seed_base, self.global_step))
