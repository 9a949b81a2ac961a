"""The LightningModule that trains and evaluates any pose network, whatever its method.

Conventions
-----------
* The network (:class:`image2sphere.nn.base.PoseNetwork`) maps ``images (B, 3, H, W)`` (and
  ``class_index (B,)`` when it was built with ``num_classes > 0``) to its own output; its
  ``output_distribution(output)`` is a :class:`~image2sphere.distributions.base.PoseDistribution`
  and ``loss(output, rotation, train_grid_level)`` its training loss per image. Nothing here depends
  on the method: I2S's loss is the cross-entropy of the grid softmax at ``train_grid_level``, a
  density family's its negative log likelihood, a regressor's its distance to the label.
* Every density method is evaluated by the same grid protocol (docs/evaluation.md); a point
  regressor (``has_density`` false) has its point estimate scored, and its log likelihood and
  spread are left out of the metrics (not available).
* Batches are dicts (:mod:`image2sphere.data`): ``image``, ``class_index``, and either
  ``rotation (B, 3, 3)`` (training) or ``rotations (B, M, 3, 3)`` with ``mask (B, M)`` (evaluation),
  optionally ``skipped``: corrupt images dropped from the batch (``dataset.on_corrupt=skip``). They are
  counted (``<stage>/skipped_images``, and ``skipped_images`` in the test metrics); a batch whose images
  were all skipped is ``None`` and is passed over.
* Metrics follow docs/evaluation.md (:mod:`image2sphere.metrics`): validation at ``val_grid_level``,
  test at ``eval_grid_level`` (spread at ``spread_grid_level``). The final test metrics are kept in
  :attr:`test_metrics` and logged as ``test/<metric>[/<class>]``. The test also scores the calibration
  of a density (HDR coverage and ECE), from the same grid sweep as the log likelihood; its random
  tie-break is a fixed draw per (image, target) pair, seeded by the image's class and dataset index.
* Recalibration (:mod:`image2sphere.recalibration`): :meth:`PoseEstimationModule.fit_recalibration`
  fits one temperature on the validation split after training; it is kept in :attr:`recalibration`
  and in checkpoints (``checkpoint["recalibration"]``). The test then also reports the log likelihood,
  HDR coverage and ECE of the recalibrated distributions (``<metric>_calibrated``); every other metric
  is the model's own. :meth:`calibrated_distribution` is the distribution to show and use: recalibrated unless
  :attr:`use_recalibration` is False.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence

import lightning.pytorch as pl
import numpy as np
import torch
from lightning.pytorch.utilities.warnings import PossibleUserWarning
from torch import nn

from image2sphere.checks import ConfigError
from image2sphere.data.common import stable_seed
from image2sphere.data.loading import PADDING
from image2sphere.distributions.base import LOG_UNIFORM_DENSITY
from image2sphere.metrics import (
    check_targets,
    density_pairs,
    fill_padding,
    hdr_coverage_counts,
    log_likelihood_pairs,
    min_angular_error_deg,
    spread_deg,
    summarize_pose_metrics,
    tie_break_uniforms,
)
from image2sphere.nn.base import method_of, set_loss_of
from image2sphere.precision import float32_region
from image2sphere.recalibration import Recalibration, ScoredPairs, fit_temperature
from image2sphere.so3.grid import (
    check_grid_levels,
    so3_grid_size,
    so3_healpix_index_to_matrix,
)
from image2sphere.training.run_config import deprecated_name
from image2sphere.training.test_cost import announce_test_cost

__all__ = ["NonFiniteLossError", "PoseEstimationModule"]

# The validation and test metrics are computed from the per-image records of every rank (_gather), so
# each rank logs the same values and Lightning's advice to reduce them across ranks does not apply.
warnings.filterwarnings(
    "ignore", message=r"It is recommended to use `self\.log\('(val|test)/", category=PossibleUserWarning
)


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
        refine: refine the test point estimate by gradient ascent on the Fourier series.
        refine_mode: the old name of ``refine`` (deprecated; one release): when not ``None``, a warning
            and its value is used.
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
        refine: bool = False,
        refine_mode: bool | None = None,
    ):
        super().__init__()
        methods = method_of(net)  # ValueError for a network that is not a pose network
        if scheduler_interval not in ("epoch", "step"):
            raise ConfigError(f"model.scheduler_interval must be 'epoch' or 'step', got {scheduler_interval!r}")
        check_grid_levels(
            train_grid_level=train_grid_level,
            val_grid_level=val_grid_level,
            eval_grid_level=eval_grid_level,
            spread_grid_level=spread_grid_level,
        )
        # Only plain values go into checkpoints (they must load with torch.load(weights_only=True));
        # the full resolved config is stored separately as ``run_config``.
        self.save_hyperparameters(logger=False, ignore=["net", "optimizer", "scheduler", "refine_mode"])
        if refine_mode is not None:
            deprecated_name("model.refine_mode", "model.refine")
            self.hparams.refine = bool(refine_mode)
        self.optimizer_factory = optimizer
        self.scheduler_factory = scheduler
        self.net = net
        self.lmax = getattr(net, "lmax", None)
        self.output_distribution, self.method_loss = methods
        self.method_set_loss = set_loss_of(net, self.method_loss)
        self.class_names = list(class_names) if class_names is not None else None
        self.test_metrics: dict[str, float] = {}
        self.skipped_images: dict[str, int] = {}
        self._records: dict[str, list[torch.Tensor]] = {}
        self._seed_base = torch.initial_seed()
        self._unindexed = 0  # test images without a dataset index seen so far (their tie-break seeds)
        self.run_config: dict | None = None  # the resolved Hydra config, stored in checkpoints
        self.recalibration: Recalibration | None = None  # the fitted temperature (fit_recalibration)
        self.use_recalibration = True  # distribution() applies it

    # ------------------------------------------------------------------ forward
    def forward(self, images: torch.Tensor, class_index: torch.Tensor | None = None) -> torch.Tensor:
        if getattr(self.net, "num_classes", 0):
            return self.net(images, class_index)
        return self.net(images)

    def calibrated_distribution(self, output: torch.Tensor):
        """The distribution of the network's ``output`` to show and use: tempered by the fitted temperature
        (:attr:`recalibration`) unless :attr:`use_recalibration` is False or none was fitted (the
        network's own ``distribution(images)`` is never recalibrated)."""
        dist = self.output_distribution(output)
        if self.recalibration is None or not self.use_recalibration or not dist.has_density:
            return dist
        return dist.tempered(self.recalibration.temperature)

    def _count_skipped(self, batch: dict | None, stage: str) -> bool:
        """Count the corrupt images left out of ``batch``; False when nothing is left of it (also for a batch
        of a distributed run's empty slots, :data:`~image2sphere.data.loading.PADDING`)."""
        if batch is PADDING:
            return False
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
        output = self(batch["image"], batch.get("class_index"))
        level = self.hparams.train_grid_level
        if "rotation" in batch:  # one label per image
            loss = self.method_loss(output, batch["rotation"], level).mean()
        else:  # every equivalent rotation (dataset.label=all): the loss averaged over them
            mask = check_targets(batch["rotations"], batch.get("mask"), len(batch["image"]))
            loss = self.method_set_loss(output, batch["rotations"], mask, level).mean()
        if not torch.isfinite(loss):
            raise NonFiniteLossError(
                f"training loss is {loss.item()} at epoch {self.current_epoch}, batch {batch_idx} "
                f"(global step {self.global_step}); the run was stopped before this step could reach a "
                "checkpoint. Lower model.optimizer.lr or check the data"
            )
        # sync_dist: in a distributed run the logged loss is the mean over the ranks' batches
        self.log(
            "train/loss",
            loss,
            prog_bar=True,
            on_step=True,
            on_epoch=True,
            batch_size=len(batch["image"]),
            sync_dist=True,
        )
        return loss

    # ------------------------------------------------------------------ evaluation
    @float32_region  # under mixed precision: the encoder in bf16/fp16, the metrics in float32
    def _evaluate(
        self, batch: dict, level: int, spread_level: int | None, calibration: bool = False
    ) -> dict[str, torch.Tensor]:
        output = self(batch["image"], batch.get("class_index"))
        dist = self.output_distribution(output)
        targets, mask = batch["rotations"], batch["mask"]
        mask = check_targets(targets, mask, dist.batch_size)
        out = {
            "class_index": batch["class_index"],
            "index": batch.get("index", torch.full_like(batch["class_index"], -1)),
        }
        if not dist.has_density:  # a point regressor: its estimate, and the loss at the first target
            out["error_deg"] = min_angular_error_deg(dist.mode().to(targets.dtype), targets, mask)
            out["loss"] = self.method_loss(output, targets[:, 0], level)
            return out
        if calibration:  # one sweep: log normaliser, argmax, log density and HDR level of every pair
            u = self._tie_break(out, mask.shape[1])
            pairs = density_pairs(dist, targets, mask, level, u)
            ll, argmax = pairs.log_density, pairs.argmax  # [B, M], NaN on padding; [B]
            out["hdr_counts"] = hdr_coverage_counts(pairs.hdr_level, mask)  # [B, len(HDR_LEVELS)]
            if self.recalibration is not None:  # the same pairs under the recalibrated distribution
                temperature, tempered = self.recalibration.temperature, pairs  # T = 1 (a degenerate fit): the same
                if temperature != 1.0:
                    tempered = density_pairs(dist.tempered(temperature), targets, mask, level, u)
                out["ll_calibrated_sum"] = tempered.log_density.to(targets.device).masked_fill(~mask, 0.0).sum(1)
                out["hdr_counts_calibrated"] = hdr_coverage_counts(tempered.hdr_level, mask)
        else:
            lse, _, argmax = dist.grid_logsumexp_and_max(level)  # [B], [B], [B]
            ll = log_likelihood_pairs(dist, targets, mask, level, log_normalizer=lse)  # [B, M], NaN on padding
        if self.hparams.refine:
            pred = dist.mode(level, refine=True).to(targets.dtype)
        else:
            pred = so3_healpix_index_to_matrix(argmax, level, dtype=targets.dtype).to(targets.device)
        ll = ll.to(targets.device)
        log_n = math.log(math.prod(so3_grid_size(level)))
        out.update(
            error_deg=min_angular_error_deg(pred, targets, mask),
            ll_sum=ll.masked_fill(~mask, 0.0).sum(1),
            ll_count=mask.sum(1),
            # -log p at the grid point nearest the rendering rotation (I2S's loss, at this level)
            loss=log_n + LOG_UNIFORM_DENSITY - ll[:, 0],
        )
        if dist.has_exact_density:  # the family's continuous density, besides the grid protocol's
            with torch.no_grad():
                exact = dist.exact_log_density(fill_padding(targets, mask).to(dist.dtype))  # [B, M]
            out["ll_exact_sum"] = exact.masked_fill(~mask, 0.0).sum(1)
        if spread_level is not None:
            out["spread"] = spread_deg(dist, targets, mask, spread_level)
        return out

    def _tie_break(self, out: dict[str, torch.Tensor], m: int) -> torch.Tensor:
        """The HDR tie-break uniforms ``(B, m)`` of a test batch: a function of each image's (class, dataset
        index) only, so every run, batch size and process draws the same; images without an index are
        numbered in the order the test loop sees them."""
        seeds = []
        for c, i in zip(out["class_index"].tolist(), out["index"].tolist(), strict=True):
            if i < 0:
                i, self._unindexed = -1 - self._unindexed, self._unindexed + 1
            seeds.append(stable_seed("test-image", c, i))
        return tie_break_uniforms(seeds, m)

    def _record(self, out: dict[str, torch.Tensor]) -> None:
        for key, value in out.items():
            self._records.setdefault(key, []).append(value.detach().cpu())

    def _summarize(self) -> dict[str, float] | None:
        """The metrics of the records of every process (:meth:`_gather`); ``None`` when no process has any.
        **Collective** in a distributed run: every rank calls it at the end of every evaluation epoch, also
        one whose share was empty or all corrupt."""
        records = {k: torch.cat(v) for k, v in self._records.items()}
        self._records = {}
        records = self._gather(records)
        if not records:
            return None
        names = self.class_names or [str(c) for c in range(int(records["class_index"].max()) + 1)]
        metrics = summarize_pose_metrics(
            records["class_index"],
            names,
            error_deg=records["error_deg"],
            ll_sum=records.get("ll_sum"),
            ll_count=records.get("ll_count"),
            spread=records.get("spread"),
            ll_exact_sum=records.get("ll_exact_sum"),
            hdr_counts=records.get("hdr_counts"),
        )
        if "ll_calibrated_sum" in records:  # the recalibrated distributions' density metrics
            calibrated = summarize_pose_metrics(
                records["class_index"],
                names,
                ll_sum=records["ll_calibrated_sum"],
                ll_count=records["ll_count"],
                hdr_counts=records["hdr_counts_calibrated"],
            )
            for key, value in calibrated.items():
                metric, _, name = key.partition("/")
                if metric != "n_images":
                    metrics[f"{metric}_calibrated" + (f"/{name}" if name else "")] = value
            metrics["temperature"] = self.recalibration.temperature
        metrics["loss"] = float(records["loss"].double().mean())
        return metrics

    def _gather(self, records: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Records of all processes, in the order of (class, dataset index), each image once.

        In a distributed run every process scores its own share of the test set; the shares are
        gathered here on every process. Our samplers give each image to one process, but a sampler that
        pads the shares with repeats (torch's ``DistributedSampler``) would score some twice: an image
        (class, index) seen more than once is kept once. Sorting makes the sums over images, and so the
        metrics, independent of how the images were shared out, equal to a single process's up to each
        image's own floating-point rounding.
        """
        trainer = self._trainer
        distributed = trainer is not None and trainer.world_size > 1 and torch.distributed.is_initialized()
        if distributed:
            gathered: list = [None] * trainer.world_size
            torch.distributed.all_gather_object(gathered, records)
            keys = dict.fromkeys(k for g in gathered for k in g)  # a rank with nothing scored sends {}
            records = {k: torch.cat([g[k] for g in gathered if k in g]) for k in keys}
        if not records:
            return records
        index = records["index"].long()
        if len(index) == 0 or bool((index < 0).any()):  # images without a dataset index: kept as they came
            return records
        key = records["class_index"].long() * (int(index.max()) + 1) + index
        if distributed:  # the first occurrence of each (class, index), in key order
            _, order = np.unique(key.numpy(), return_index=True)
        else:
            order = np.argsort(key.numpy(), kind="stable")
        order = torch.from_numpy(order)
        return {k: v[order] for k, v in records.items()}

    def on_train_epoch_end(self) -> None:
        if self.skipped_images.get("train"):
            self.log("train/skipped_images", float(self.skipped_images["train"]))

    def validation_step(self, batch: dict | None, batch_idx: int) -> None:
        if self._count_skipped(batch, "val"):
            self._record(self._evaluate(batch, self.hparams.val_grid_level, None))

    def on_validation_epoch_end(self) -> None:
        m = self._summarize()
        if m is None:
            return
        keys = ("loss", "log_likelihood", "median_error_deg", "acc15")  # log_likelihood: density methods only
        self.log_dict({f"val/{k}": m[k] for k in keys if k in m}, prog_bar=True, sync_dist=False)
        # each class's curve for the loggers (one shape can sit at uniform while the mean rises); not in the bar
        per_class = {f"val/{k}": v for k, v in m.items() if "/" in k and k.split("/", 1)[0] in keys}
        if per_class:
            self.log_dict(per_class, prog_bar=False, sync_dist=False)

    def test_step(self, batch: dict | None, batch_idx: int) -> None:
        if self._count_skipped(batch, "test"):
            level, spread_level = self.hparams.eval_grid_level, self.hparams.spread_grid_level
            self._record(self._evaluate(batch, level, spread_level, calibration=True))

    def on_test_start(self) -> None:
        trainer = self._trainer
        if trainer is None or not trainer.is_global_zero:
            return
        batches = sum(trainer.num_test_batches)
        loader = trainer.test_dataloaders
        loader = loader[0] if isinstance(loader, (list, tuple)) else loader
        batch_size = getattr(loader, "batch_size", None)
        if batch_size and math.isfinite(batches):  # this process's share: what it will have to score
            n_images = int(batches) * batch_size
            dataset = getattr(loader, "dataset", None)
            if hasattr(dataset, "__len__"):  # the last batch may be partial
                n_images = min(n_images, -(-len(dataset) // max(1, trainer.world_size)))
            level, spread_level = self.hparams.eval_grid_level, self.hparams.spread_grid_level
            announce_test_cost(self, n_images, level, spread_level, "eval_grid_level")

    def on_test_epoch_start(self) -> None:
        self.skipped_images.pop("test", None)
        self._unindexed = 0

    def on_test_epoch_end(self) -> None:
        self.test_metrics = self._summarize() or {}
        if self.skipped_images.get("test"):
            # the metrics do not cover every test image: say so next to them
            self.test_metrics["skipped_images"] = float(self.skipped_images["test"])
        self.log_dict({f"test/{k}": v for k, v in self.test_metrics.items()}, sync_dist=False)

    # ------------------------------------------------------------------ recalibration
    @torch.no_grad()
    @float32_region
    def fit_recalibration(self, dataloader, level: int | None = None, split: str = "val") -> Recalibration | None:
        """Fit the temperature on ``dataloader``'s images (the validation split) and keep it in
        :attr:`recalibration` (:func:`~image2sphere.recalibration.fit_temperature`). ``None`` (nothing
        fitted) for a point regressor or an empty ``dataloader``. ``level``: the grid it is scored on
        (default: the test's, ``eval_grid_level``). In a distributed run each process scores its share
        and the sums are added."""
        level = self.hparams.eval_grid_level if level is None else level
        was_training = self.training
        self.eval()
        batches, n_images = [], 0
        try:
            for batch in dataloader:
                if batch is None or batch is PADDING:
                    continue
                batch = self.transfer_batch_to_device(batch, self.device, 0)
                output = self(batch["image"], batch.get("class_index"))
                dist = self.output_distribution(output)
                if not dist.has_density:
                    return None
                targets, mask = batch["rotations"], batch["mask"]
                mask = check_targets(targets, mask, dist.batch_size)
                index = batch.get("index", torch.full_like(batch["class_index"], -1))
                seeds = [stable_seed("recalibration", c, i) for c, i in zip(batch["class_index"].tolist(),
                                                                            index.tolist(), strict=True)]  # fmt: skip
                u = tie_break_uniforms(seeds, mask.shape[1])
                batches.append(ScoredPairs(dist, targets, mask, u, batch["class_index"]))
                n_images += len(targets)
        finally:
            self.train(was_training)
        trainer = self._trainer
        reduce = None
        if trainer is not None and trainer.world_size > 1 and torch.distributed.is_initialized():
            reduce = self._sum_over_processes
            # the split's size, not this rank's share: what the fit reports, and the same grid on every rank
            # (and as on one process) where its size decides the grid (recalibration.fit_level)
            n_images = int(reduce(torch.tensor([n_images], dtype=torch.int64)).item())
        if not batches and reduce is None:  # nothing to fit on (a distributed run has checked its loader)
            return None
        num_classes = len(self.class_names) if self.class_names else None
        self.recalibration = fit_temperature(
            batches, level, num_classes=num_classes, split=split, n_images=n_images, reduce=reduce
        )
        return self.recalibration

    def _sum_over_processes(self, totals: torch.Tensor) -> torch.Tensor:
        totals = totals.to(self.device)
        torch.distributed.all_reduce(totals)
        return totals

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
        if self.recalibration is not None:
            checkpoint["recalibration"] = self.recalibration.to_dict()
        if self.run_config is not None:
            checkpoint["run_config"] = self.run_config

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        if checkpoint.get("class_names") is not None:
            self.class_names = list(checkpoint["class_names"])
        if checkpoint.get("recalibration") is not None:  # e.g. train=false ckpt_path=...: the test reports it
            self.recalibration = Recalibration.from_dict(checkpoint["recalibration"])

    # ------------------------------------------------------------------ exact resume
    def on_train_start(self) -> None:
        self.recalibration = None  # a temperature fitted to other weights does not apply (fitted again after)

    def on_fit_start(self) -> None:
        self._seed_base = torch.initial_seed()  # the run's seed (seed_everything), before any reseeding

    def on_train_batch_start(self, batch: dict, batch_idx: int) -> None:
        # The network's own randomness (the projector's random grid subset) comes from torch's global
        # generator. Reseeding it from (seed, global step) before every step makes each step's draws
        # independent of everything before it, so a run resumed from a checkpoint, one written at an
        # epoch's end or in the middle of an epoch, continues exactly as the uninterrupted run (the data
        # order and labels follow the same rule, see image2sphere.training.checkpoint).
        torch.manual_seed(stable_seed("train-step", self._seed_base, self.global_step))
