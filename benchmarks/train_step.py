"""Benchmark: one I2S training step at the paper's size, float32 against bf16 autocast, and the level-5
evaluation, on the device at hand (a GPU when there is one, else the CPU).

The network is ``conf/model/i2s.yaml`` composed as a training run composes it (``encoder=resnet50
dataset.image_size=224``; random weights), the paper's batch of 64, the loss on the training grid
(``model.train_grid_level``, 3). Measured in one run:

1. **training step** (forward, loss, backward, and the paper's optimiser as ``conf/optimizer/sgd.yaml``
   builds it: SGD with Nesterov momentum, ``fused: true``; ``--optimizer adam``: the built-in run's) in
   float32 and under ``torch.autocast(dtype=torch.bfloat16)``, as ``trainer.precision=bf16-mixed`` runs
   it, and in float32 with the optimiser unfused (``fused=False``: PyTorch's default, one kernel per
   weight tensor): the median of ``--repeats`` steps after ``--warmup`` untimed ones, the cases taking
   turns step by step; images per second, the bf16 / float32 and the fused / unfused ratios, and the
   optimiser's update alone. The losses of the same batch and weights are printed side by side: the SO(3)
   head runs in float32 under autocast, so they differ only by the encoder's rounding;
2. **evaluation** of the level-5 grid (2,359,296 rotations) for a batch: ``grid_logsumexp_and_max(5)``
   (the normaliser and the mode, what the test loop computes per image), median per image; the first
   call, which builds the grid evaluator, is timed apart.

On a GPU every timed region ends with ``torch.cuda.synchronize()``.

Usage::

    python benchmarks/train_step.py                         # paper size on the GPU (or the CPU)
    python benchmarks/train_step.py --batch 2 --image-size 64 --encoder resnet18 --repeats 1   # smoke
    python benchmarks/train_step.py --encoder resnet18 --image-size 96 --batch 32 --optimizer adam --level 4
                                                            # the built-in run's step
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from contextlib import nullcontext
from pathlib import Path

os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

import torch  # noqa: E402
from hydra.utils import instantiate  # noqa: E402

from _machine import cpu_model  # noqa: E402  (benchmarks/_machine.py, beside this script)
from heads import compose_cfg  # noqa: E402  (benchmarks/heads.py, beside this script)
from image2sphere.nn.base import method_of  # noqa: E402
from image2sphere.so3.rotations import random_rotations  # noqa: E402


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn, device: torch.device, repeats: int, warmup: int) -> float:
    """Median wall time of ``fn()`` over ``repeats`` runs after ``warmup`` untimed runs."""
    for _ in range(warmup):
        fn()
    sync(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--encoder", default="resnet50")
    p.add_argument("--image-size", type=int, default=224)
    p.add_argument("--optimizer", default="sgd", choices=["sgd", "adam"], help="conf/optimizer/<name>.yaml")
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--eval-batch", type=int, default=16)
    p.add_argument("--level", type=int, default=5, help="evaluation grid level")
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = p.parse_args()
    device = torch.device(args.device)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True
        name = torch.cuda.get_device_name(device)
    else:
        name = cpu_model()
    print(f"device: {name}; torch {torch.__version__}")
    print(f"I2S, {args.encoder} at {args.image_size} px, batch {args.batch}, optimizer={args.optimizer}\n")

    with tempfile.TemporaryDirectory() as tmp:
        overrides = ["model=i2s", f"optimizer={args.optimizer}", f"encoder={args.encoder}",
                     f"dataset.image_size={args.image_size}"]  # fmt: skip
        cfg = compose_cfg(Path(tmp), overrides)
    optimizer = instantiate(cfg.model.optimizer)  # a partial: called with the parameters
    grid_level = int(cfg.model.train_grid_level)
    torch.manual_seed(0)
    net = instantiate(cfg.model.net).to(device)
    output_distribution, loss_fn = method_of(net)
    images = torch.randn(args.batch, 3, args.image_size, args.image_size, device=device)
    rotations = random_rotations(args.batch).to(device)

    # the cases' steps interleaved (one step of each in turn, each case with its own optimiser state), so
    # that a machine that speeds up or slows down during the run, and the first allocations, touch all alike
    cases = {"float32": (None, True), "bf16 autocast": (torch.bfloat16, True), "float32 unfused": (None, False)}
    optimizers = {label: optimizer(params=net.parameters(), fused=fused) for label, (_, fused) in cases.items()}
    net.train()
    step_times: dict[str, list[float]] = {label: [] for label in cases}
    update_times: dict[str, list[float]] = {label: [] for label in cases}

    def context(dtype):
        return torch.autocast(device.type, dtype=dtype) if dtype is not None else nullcontext()

    for label, (dtype, _) in cases.items():
        with torch.no_grad(), context(dtype):  # the loss of the same weights and batch, before any step
            first_loss = float(loss_fn(net(images), rotations, grid_level).mean())
        print(f"loss of the first batch, {label:15s}: {first_loss:.5f}")
    for rep in range(args.warmup + args.repeats):
        for label, (dtype, _) in cases.items():
            opt = optimizers[label]
            sync(device)
            t0 = time.perf_counter()
            opt.zero_grad(set_to_none=True)
            with context(dtype):
                loss = loss_fn(net(images), rotations, grid_level).mean()
            loss.backward()
            sync(device)
            t1 = time.perf_counter()
            opt.step()
            sync(device)
            t2 = time.perf_counter()
            if rep >= args.warmup:
                step_times[label].append(t2 - t0)
                update_times[label].append(t2 - t1)
    results = {label: statistics.median(v) for label, v in step_times.items()}
    updates = {label: statistics.median(v) for label, v in update_times.items()}
    print()
    for label, seconds in results.items():
        print(
            f"training step, {label:15s}: {seconds * 1e3:8.1f} ms  ({args.batch / seconds:7.1f} images/s), "
            f"the update {updates[label] * 1e3:.1f} ms"
        )
    print(f"bf16 / float32 step time: {results['bf16 autocast'] / results['float32']:.2f}x")
    fused, unfused = "float32", "float32 unfused"
    print(
        f"fused / unfused optimiser: {results[fused] / results[unfused]:.2f}x the training step, "
        f"{updates[fused] / updates[unfused]:.2f}x the update alone\n"
    )

    net.eval()
    with torch.no_grad():
        output = net(images[: args.eval_batch])
        dist = output_distribution(output)
        sync(device)
        t0 = time.perf_counter()
        dist.grid_logsumexp_and_max(args.level)
        sync(device)
        first = time.perf_counter() - t0
        seconds = timed(lambda: output_distribution(output).grid_logsumexp_and_max(args.level), device, 3, 1)
    print(
        f"level-{args.level} evaluation (normaliser and mode), batch {args.eval_batch}: "
        f"{seconds / args.eval_batch * 1e3:.2f} ms per image (first call, building the evaluator: {first:.2f} s)"
    )
    if device.type == "cuda":
        print(f"peak GPU memory: {torch.cuda.max_memory_allocated(device) / 2**30:.2f} GiB")


if __name__ == "__main__":
    main()
