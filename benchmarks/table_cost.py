"""Benchmark: what each of the paper's tables costs to train, per job and in all (``table=tableN``).

For every job of a table's sweep (``conf/table/<table>.yaml``, expanded as ``hydra/sweeper=table``
expands it), the job's config is composed as the training run would compose it, and its network is
built (random weights) at the job's own image size and encoder. For each distinct network:

* **FLOPs per training image**: ``torch.utils.flop_counter.FlopCounterMode`` over one training step
  (forward, the method's own loss on the job's training grid, backward) on a batch of ``--batch``
  images, divided by the batch. It counts the matrix products and convolutions (the bulk of the
  work), not element-wise operations;
* **CPU seconds per training image** on this machine: the same step, timed after one warm-up.

Images per epoch come from the published datasets' sizes (below; PASCAL3D+'s real training set is an
estimate, stated as such), times the job's ``trainer.max_epochs``. Evaluation (one forward pass per
test image plus the level-5 grid) is small beside 40 training epochs and is left out.

GPU-hours are *estimated*, not measured: training FLOPs divided by an assumed sustained throughput,
``--gpu-tflops`` (default 30 TFLOP/s: the order of what a plain float32/TF32 PyTorch training loop of
a ResNet sustains on one A100/H100-class GPU; mixed precision is faster). Treat them as within a
factor of 2-3. CPU-hours are the measured CPU step time times the images, on this machine.

Usage::

    python benchmarks/table_cost.py                      # every table
    python benchmarks/table_cost.py --tables table7 --batch 2
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

import torch  # noqa: E402
from hydra.utils import instantiate  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402
from torch.utils.flop_counter import FlopCounterMode  # noqa: E402

from hydra_plugins.image2sphere_sweeper.table_sweeper import expand_grids  # noqa: E402
from image2sphere.data.modelnet_labels import MODELNET10_TRAIN_INSTANCES  # noqa: E402
from image2sphere.nn.base import method_of  # noqa: E402
from image2sphere.so3.rotations import random_rotations  # noqa: E402

try:  # run as `python benchmarks/table_cost.py`: heads.py is a sibling file
    from heads import compose_cfg
except ImportError:  # imported as benchmarks.table_cost
    from benchmarks.heads import compose_cfg

REPO = Path(__file__).resolve().parents[1]
SYMSOL_TRAIN_PER_SHAPE = 45_000  # the release's training images per shape
# PASCAL3D+ 1.1 real training objects after the paper's filtering (VOC train + ImageNet train/val,
# no occluded, truncated or difficult objects): an estimate, ~12,000; an epoch adds
# synthetic_ratio x that many RenderForCNN images.
PASCAL3D_REAL_ESTIMATE = 12_000


def images_per_epoch(dataset) -> tuple[int, str]:
    target = dataset._target_.rsplit(".", 1)[-1]
    if target == "ModelNet10DataModule":
        views = 100 if "100V" in dataset.train_split else 20
        return sum(MODELNET10_TRAIN_INSTANCES.values()) * views, f"ModelNet10-SO(3) {dataset.train_split}"
    if target == "SymsolDataModule":
        shapes = [dataset.shape] if dataset.get("shape") else list(dataset.shapes)
        per_shape = dataset.num_views or SYMSOL_TRAIN_PER_SHAPE
        return len(shapes) * per_shape, f"SYMSOL {'+'.join(shapes)} x {per_shape}"
    if target == "Pascal3DDataModule":
        ratio = float(dataset.get("synthetic_ratio") or 0)
        n = round(PASCAL3D_REAL_ESTIMATE * (1 + ratio))
        return n, f"PASCAL3D+ ~{PASCAL3D_REAL_ESTIMATE} real (estimate) x (1 + {ratio:g} synthetic)"
    raise ValueError(f"no size known for {target}")


def step_cost(cfg, batch: int) -> tuple[float, float]:
    """FLOPs and CPU seconds of one training step, per image."""
    torch.manual_seed(0)
    net = instantiate(cfg.model.net)
    _, loss_fn = method_of(net)
    size = int(cfg.dataset.image_size)
    images = torch.randn(batch, 3, size, size)
    rotations = random_rotations(batch, dtype=torch.float32)
    level = int(cfg.model.train_grid_level)
    classes = torch.zeros(batch, dtype=torch.long) if getattr(net, "num_classes", 0) else None

    def step():
        net.zero_grad(set_to_none=True)
        loss_fn(net(images, classes), rotations, level).mean().backward()

    counter = FlopCounterMode(display=False)
    with counter:
        step()
    start = time.perf_counter()
    step()
    seconds = time.perf_counter() - start
    return counter.get_total_flops() / batch, seconds / batch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tables", default=",".join(sorted(p.stem for p in (REPO / "conf/table").glob("*.yaml"))))
    parser.add_argument("--batch", type=int, default=2)
    parser.add_argument("--gpu-tflops", type=float, default=30.0)
    args = parser.parse_args()
    from hydra.core.override_parser.overrides_parser import OverridesParser

    machine = platform.processor() or platform.machine()
    print(f"# {machine}, {torch.get_num_threads()} threads, torch {torch.__version__}")
    print(f"# GPU-hours: estimated at an assumed {args.gpu_tflops:g} TFLOP/s sustained (not measured)\n")
    cache: dict[str, tuple[float, float]] = {}
    parser_ = OverridesParser.create()
    with tempfile.TemporaryDirectory() as tmp:
        for table in args.tables.split(","):
            base = compose_cfg(Path(tmp), [f"table={table}"])
            sweep = base.hydra.sweeper
            jobs = expand_grids(parser_, OmegaConf.to_container(sweep.params), OmegaConf.to_container(sweep.grids))
            total_flops = total_cpu = 0.0
            print(f"## {table}: {len(jobs)} jobs")
            print(f"{'job':<70} {'GFLOP/img':>9} {'CPU s/img':>9} {'img/epoch':>9} {'epochs':>6} {'GPU-h':>6}")
            for job in jobs:
                cfg = compose_cfg(Path(tmp), [f"table={table}", *job])
                key = OmegaConf.to_yaml(cfg.model.net, resolve=True) + str(cfg.model.train_grid_level)
                if key not in cache:
                    cache[key] = step_cost(cfg, args.batch)
                flops, cpu = cache[key]
                n, what = images_per_epoch(cfg.dataset)
                epochs = int(cfg.trainer.max_epochs)
                job_flops = flops * n * epochs
                total_flops += job_flops
                total_cpu += cpu * n * epochs
                gpu_h = job_flops / (args.gpu_tflops * 1e12) / 3600
                print(f"{' '.join(job):<70} {flops / 1e9:>9.1f} {cpu:>9.2f} {n:>9} {epochs:>6} {gpu_h:>6.1f}")
            gpu_hours = total_flops / (args.gpu_tflops * 1e12) / 3600
            print(f"total: {total_flops / 1e15:.0f} PFLOP; ~{gpu_hours:.0f} GPU-hours (estimate); "
                  f"{total_cpu / 3600:.0f} CPU-hours on this machine (measured per image)\n")  # fmt: skip


if __name__ == "__main__":
    main()
