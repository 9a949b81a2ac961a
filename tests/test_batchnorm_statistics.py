"""``callbacks.batchnorm_statistics``: BatchNorm's running statistics recomputed from the current weights.

Quick tier: a tiny matrix Fisher network whose encoder has one BatchNorm layer, trained in this process
on 40 random images (5 batches of 8 per epoch).
"""

from __future__ import annotations

import functools
import math

import lightning.pytorch as pl
import pytest
import torch
from torch import nn
from torch.utils.data import DataLoader

from conftest import haar_rotations
from image2sphere.data.loading import EpochShuffleSampler
from image2sphere.nn import MatrixFisherNet
from image2sphere.training import PoseEstimationModule
from image2sphere.training.callbacks import BatchNormStatistics, recompute_batchnorm_statistics

IMAGE_SIZE, N_IMAGES, BATCH = 16, 40, 8


class BNEncoder(nn.Module):
    out_channels = 4

    def __init__(self):
        super().__init__()
        self.conv = nn.Conv2d(3, self.out_channels, 3, stride=2, padding=1)
        self.norm = nn.BatchNorm2d(self.out_channels)

    def feature_size(self, image_size):
        return (math.ceil(image_size / 2),) * 2

    def forward(self, images):
        return torch.relu(self.norm(self.conv(images)))


def _items() -> list[dict]:
    g = torch.Generator().manual_seed(0)
    # the images' mean and spread differ from BatchNorm's start (0, 1), so the statistics move
    images = 3.0 + 2.0 * torch.randn(N_IMAGES, 3, IMAGE_SIZE, IMAGE_SIZE, generator=g)
    rotations = haar_rotations(N_IMAGES, seed=1, dtype=torch.float32)
    return [{"image": images[i], "rotation": rotations[i], "index": i} for i in range(N_IMAGES)]


def _eval_items() -> list[dict]:
    return [
        {
            "image": it["image"],
            "rotations": it["rotation"][None],
            "mask": torch.ones(1, dtype=torch.bool),
            "index": it["index"],
            "class_index": 0,
        }
        for it in _items()[:8]
    ]


class _Record(pl.Callback):
    """The images of each training batch by epoch, the loss of each step, and whether every module is in
    evaluation mode during validation."""

    def __init__(self):
        self.batches: dict[int, list[torch.Tensor]] = {}
        self.losses: list[float] = []
        self.eval_mode_in_validation: list[bool] = []

    def on_train_batch_start(self, trainer, module, batch, batch_idx):
        self.batches.setdefault(trainer.current_epoch, []).append(batch["image"].clone())

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
        self.losses.append(float(outputs["loss"]))

    def on_validation_batch_start(self, trainer, module, batch, batch_idx, dataloader_idx=0):
        self.eval_mode_in_validation.append(not any(m.training for m in module.modules()))


def _fit(callbacks: list[pl.Callback], epochs: int = 2, train: DataLoader | None = None) -> PoseEstimationModule:
    torch.manual_seed(0)
    net = MatrixFisherNet(BNEncoder(), IMAGE_SIZE, hidden=8)
    module = PoseEstimationModule(
        net, optimizer=functools.partial(torch.optim.Adam, lr=0.01), class_names=["a"],
        train_grid_level=1, val_grid_level=1, eval_grid_level=1, spread_grid_level=1,
    )  # fmt: skip
    if train is None:
        train = DataLoader(_items(), batch_size=BATCH, sampler=EpochShuffleSampler(N_IMAGES, seed=3))
    trainer = pl.Trainer(
        accelerator="cpu", devices=1, max_epochs=epochs, logger=False, enable_checkpointing=False,
        enable_progress_bar=False, enable_model_summary=False, num_sanity_val_steps=0, callbacks=callbacks,
    )  # fmt: skip
    trainer.fit(module, train, DataLoader(_eval_items(), batch_size=4))
    return module


@pytest.mark.filterwarnings("ignore::UserWarning")  # Lightning's notes on workers and tiny data sets
def test_statistics_are_the_mean_over_the_epochs_first_batches_with_the_final_weights():
    """After training, the running mean and variance are the averages, over the first ``num_batches``
    batches of the last epoch (as the trainer drew them), of each batch's mean and unbiased variance of
    the BatchNorm layer's input, computed here with the final weights by a forward hook; validation runs
    with every module in evaluation mode."""
    record = _Record()
    module = _fit([BatchNormStatistics(num_batches=3), record])
    norm = module.net.encoder.norm
    means, variances = [], []
    hook = norm.register_forward_hook(lambda m, args, out: captured.append(args[0].detach()))
    module.eval()
    with torch.no_grad():
        for images in record.batches[1][:3]:  # the last epoch's first three batches
            captured: list[torch.Tensor] = []
            module.net(images)
            x = captured[0].transpose(0, 1).flatten(1)  # [channels, batch * h * w]
            means.append(x.mean(1))
            variances.append(x.var(1, unbiased=True))
    hook.remove()
    torch.testing.assert_close(norm.running_mean, torch.stack(means).mean(0), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(norm.running_var, torch.stack(variances).mean(0), rtol=1e-5, atol=1e-6)
    assert record.eval_mode_in_validation and all(record.eval_mode_in_validation)
    assert norm.momentum == 0.1  # update_bn's cumulative average was switched off again


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_training_follows_the_same_path_with_and_without_the_callback():
    """Training batches are normalised with their own statistics, and the callback leaves the random
    state alone: the losses and the weights are exactly those of a run without it; only the running
    statistics (what evaluation uses) differ."""
    with_, without = _Record(), _Record()
    a = _fit([BatchNormStatistics(num_batches=2), with_])
    b = _fit([without])
    assert with_.losses == without.losses and len(with_.losses) == 2 * math.ceil(N_IMAGES / BATCH)
    for (name, p), q in zip(a.named_parameters(), b.parameters(), strict=True):
        assert torch.equal(p, q), name
    assert not torch.allclose(a.net.encoder.norm.running_var, b.net.encoder.norm.running_var, rtol=1e-3)


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_a_loader_without_a_batch_size_is_named_in_a_warning_and_left_alone(caplog):
    """A training loader built from a batch sampler has no batch size to rebuild batches with: the callback
    says so once and leaves the running averages as training kept them (those of a run without it)."""
    from torch.utils.data import BatchSampler, SequentialSampler

    def loader() -> DataLoader:
        return DataLoader(_items(), batch_sampler=BatchSampler(SequentialSampler(range(N_IMAGES)), BATCH, False))

    with caplog.at_level("WARNING", logger="image2sphere.training.callbacks"):
        a = _fit([BatchNormStatistics(num_batches=2)], train=loader())
    b = _fit([], train=loader())
    ours = [r.getMessage() for r in caplog.records if r.name == "image2sphere.training.callbacks"]
    assert len(ours) == 1 and "not one DataLoader with a batch size" in ours[0]  # once, over two epochs
    assert torch.equal(a.net.encoder.norm.running_var, b.net.encoder.norm.running_var)


@pytest.mark.parametrize("value", [0, -1, 2.5, True, "200"])
def test_num_batches_must_be_a_positive_integer(value):
    """Quick. A bad value names its config key."""
    with pytest.raises(ValueError, match="callbacks.batchnorm_statistics.num_batches"):
        BatchNormStatistics(num_batches=value)


def test_two_ranks_average_their_shares_to_the_one_process_mean():
    """Quick. In a distributed run rank ``r`` averages over its share of the epoch's order (every second
    image from ``r`` on) and the ranks' statistics are averaged (``reduce``, here the other rank's values
    fed in the order the layers are visited). The two shares of ``n`` batches are the images of the first
    ``2 n`` batches of one process, so the mean equals one process's over those batches exactly (in
    float64: equal batch sizes); the variance, a mean of within-batch variances, differs only by batching."""
    import copy

    torch.manual_seed(0)
    net = MatrixFisherNet(BNEncoder(), IMAGE_SIZE, hidden=8).double()
    items = [{**it, "image": it["image"].double()} for it in _items()]
    loader = DataLoader(items, batch_size=4, sampler=EpochShuffleSampler(N_IMAGES, seed=3))
    single, rank0, rank1 = (copy.deepcopy(net) for _ in range(3))
    recompute_batchnorm_statistics(single, loader, num_batches=4, epoch=2)
    recompute_batchnorm_statistics(rank1, loader, num_batches=2, epoch=2, world_size=2, rank=1)
    other = [
        b.clone() for m in rank1.modules() if isinstance(m, nn.BatchNorm2d) for b in (m.running_mean, m.running_var)
    ]
    recompute_batchnorm_statistics(rank0, loader, num_batches=2, epoch=2, world_size=2, rank=0,
                                   reduce=lambda t: (t + other.pop(0)) / 2)  # fmt: skip
    assert not other  # every buffer was reduced
    a, b = single.encoder.norm, rank0.encoder.norm
    torch.testing.assert_close(b.running_mean, a.running_mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(b.running_var, a.running_var, rtol=0.2, atol=0.0)
    # the reduced variance exactly: each rank's mean of its batches' unbiased variances (BatchNorm's cumulative
    # average), then the mean over the two ranks, computed here from the layer's input
    per_rank = []
    for r in (0, 1):
        order = EpochShuffleSampler(N_IMAGES, 3, None, None, 2, r)
        order.epoch = 2
        indices = list(iter(order))[:8]
        with torch.no_grad():
            variances = [
                net.encoder.conv(torch.stack([items[i]["image"] for i in indices[k : k + 4]])).var(dim=(0, 2, 3))
                for k in (0, 4)
            ]  # [channels] each, unbiased
        per_rank.append(torch.stack(variances).mean(0))
    torch.testing.assert_close(b.running_var, (per_rank[0] + per_rank[1]) / 2, rtol=1e-12, atol=1e-12)
    assert not torch.equal(rank1.encoder.norm.running_mean, b.running_mean)  # rank 1 alone saw other images
