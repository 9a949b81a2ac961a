"""Benchmark: what ``callbacks.batchnorm_statistics`` adds to an epoch of the built-in default run.

The network is the default ``conf/model/i2s.yaml`` as a training run composes it (ResNet-18, 96 px,
lmax 6; random weights) at the default batch of 32. Measured in one run, each the median of
``--repeats`` after ``--warmup`` untimed ones:

1. a **training step** (forward, loss on the training grid, backward, Adam step);
2. a **statistics pass** over one batch: the forward pass in training mode without gradients that
   :func:`torch.optim.swa_utils.update_bn` makes for each of the callback's batches.

It prints the ratio of the two and what the callback's ``num_batches`` passes (50 by default) add to an
epoch of ``--steps-per-epoch`` training steps (144 in the built-in default run: 4,600 training images
in batches of 32), once per epoch (the callback runs once per validation).

Usage::

    python benchmarks/batchnorm_statistics.py
    python benchmarks/batchnorm_statistics.py --repeats 2 --warmup 1    # smoke
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import torch
from hydra.utils import instantiate

from _machine import cpu_model  # benchmarks/_machine.py, beside this script
from heads import compose_cfg, median_time  # benchmarks/heads.py, beside this script
from image2sphere.nn.base import method_of
from image2sphere.so3.rotations import random_rotations


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--num-batches", type=int, default=50, help="callbacks.batchnorm_statistics.num_batches")
    p.add_argument("--steps-per-epoch", type=int, default=144)
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--warmup", type=int, default=2)
    args = p.parse_args()
    print(f"device: {cpu_model()}, {torch.get_num_threads()} threads; torch {torch.__version__}")

    with tempfile.TemporaryDirectory() as tmp:
        cfg = compose_cfg(Path(tmp), [])
    size, level = int(cfg.dataset.image_size), int(cfg.model.train_grid_level)
    print(f"default I2S: {cfg.encoder._target_.rsplit('.', 1)[-1]} depth {cfg.encoder.depth}, {size} px, "
          f"lmax {cfg.lmax}, batch {args.batch}\n")  # fmt: skip
    torch.manual_seed(0)
    net = instantiate(cfg.model.net).train()
    _, loss_fn = method_of(net)
    images = torch.randn(args.batch, 3, size, size)
    rotations = random_rotations(args.batch)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)

    def step() -> None:
        opt.zero_grad(set_to_none=True)
        loss_fn(net(images), rotations, level).mean().backward()
        opt.step()

    @torch.no_grad()
    def statistics_pass() -> None:
        net(images)

    train = median_time(step, args.repeats, args.warmup)
    stats = median_time(statistics_pass, args.repeats, args.warmup)
    epoch = args.steps_per_epoch * train
    added = args.num_batches * stats
    print(f"training step:                 {train * 1e3:8.1f} ms")
    print(f"statistics pass (one batch):   {stats * 1e3:8.1f} ms   ({stats / train:.2f} x a training step)")
    print(f"{args.num_batches} passes per epoch of {args.steps_per_epoch} steps: {added:.1f} s on {epoch:.1f} s, "
          f"+{added / epoch:.0%} of the epoch's training steps")  # fmt: skip


if __name__ == "__main__":
    main()
