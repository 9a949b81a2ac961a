"""Benchmark: cost of every pose method's head, with and without the image encoder, against I2S.

Every method is the network of its ``conf/model/<name>.yaml`` (composed from ``conf/train.yaml`` with
``model=<name> encoder=<encoder> dataset.image_size=<image size>``, as a training run would build it).
For each method, in one run (I2S is always measured: it is the reference of every ratio):

1. **Head alone (encoder excluded).** The encoder's feature map of one batch of random images is
   computed once; the net's encoder is then replaced by a module that returns that fixed map (same
   ``out_channels`` and ``feature_size``), so that only the head is timed:

   * training step per batch: forward, the method's own loss (``net.loss`` at the config's
     ``train_grid_level``, 3), ``backward``, an SGD step (lr 1e-3, Nesterov momentum 0.9);
   * evaluation per image at grid level ``--level``: ``output_distribution(output)
     .grid_logsumexp_and_max(level)`` for ``--eval-batch`` images (the head's output computed
     beforehand, in eval mode, without gradients), divided by the number of images. The point
     regressors (regression_6d, regression_9d, spherical_regression, bin_delta, i2s_icosahedral) have
     no density and no grid evaluation: their time is that of ``output_distribution(output).mode()``;
   * parameters of the head (every parameter but the encoder's).

2. **Whole network (encoder included).** Training step per batch as above, with the real encoder
   (random initialisation) on random images.

Times are medians of ``--repeats`` runs after one untimed warm-up run (``time.perf_counter``); the
warm-up also pays one-time costs such as building I2S's level-``level`` grid evaluator. Ratios are
method / I2S (below 1: cheaper than I2S). Everything runs on the CPU in float32.

Usage::

    python benchmarks/heads.py                                  # all methods, ResNet-50 at 224 px
    python benchmarks/heads.py --methods i2s,matrix_fisher --level 4 --eval-batch 2
    OMP_NUM_THREADS=1 python benchmarks/heads.py --quick        # smoke run (ResNet-18, 64 px, level 3)
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

# Before torch's first allocation, as `import image2sphere` would do (see src/image2sphere/__init__.py).
os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

import torch  # noqa: E402
from hydra import compose, initialize  # noqa: E402
from hydra.core.global_hydra import GlobalHydra  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from hydra.utils import instantiate  # noqa: E402
from omegaconf import DictConfig, open_dict  # noqa: E402
from torch import nn  # noqa: E402

from _machine import cpu_model, load_line  # noqa: E402  (benchmarks/_machine.py, beside this script)
from image2sphere.nn.base import method_of  # noqa: E402
from image2sphere.so3.rotations import random_rotations  # noqa: E402
from image2sphere.training import register_resolvers  # noqa: E402

METHODS = (
    "i2s",
    "fourier_mlp",
    "ipdf",
    "matrix_fisher",
    "rotation_laplace",
    "bingham",
    "von_mises",
    "regression_6d",
    "regression_9d",
    "viewpoint_bins",
    "spherical_regression",
    "bin_delta",
    "i2s_icosahedral",
    "wigner_regression",
    "rotation_flow",
)
REFERENCE = "i2s"
CONF = Path(__file__).resolve().parents[1] / "conf"
QUICK = {"batch": 4, "eval_batch": 1, "level": 3, "image_size": 64, "encoder": "resnet18", "repeats": 1}


# ---------------------------------------------------------------------------------------------- helpers
def compose_cfg(tmp_path: Path, overrides: list[str]) -> DictConfig:
    """The real ``conf/train.yaml`` with ``overrides``, composed outside a Hydra job, every path moved
    into ``tmp_path`` (as tests/test_configs.py does)."""
    register_resolvers()
    GlobalHydra.instance().clear()
    with initialize(version_base="1.3", config_path="../conf"):
        cfg = compose(config_name="train", return_hydra_config=True, overrides=list(overrides))
    with open_dict(cfg):
        cfg.paths.root_dir = str(tmp_path)
        cfg.paths.data_dir = str(tmp_path / "data")
        cfg.paths.log_dir = str(tmp_path / "logs")
        cfg.paths.output_dir = str(tmp_path / "out")
        cfg.hydra.runtime.output_dir = str(tmp_path / "out")
        cfg.hydra.job.num = 0
    HydraConfig().set_config(cfg)
    return cfg


def median_time(fn, repeats: int, warmup: int = 1) -> float:
    """Median wall time of ``fn()`` over ``repeats`` runs after ``warmup`` untimed runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def n_params(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


class FixedEncoder(nn.Module):
    """Stands in for an encoder: returns the first ``len(images)`` rows of a fixed feature map, and
    has the real encoder's ``out_channels`` and ``feature_size``. No parameters, no gradient."""

    def __init__(self, features: torch.Tensor, encoder: nn.Module):
        super().__init__()
        self.register_buffer("features", features.detach().clone())
        self.out_channels = encoder.out_channels
        self.depth = getattr(encoder, "depth", None)
        self._feature_size = encoder.feature_size

    def feature_size(self, image_size: int | tuple[int, int]) -> tuple[int, int]:
        return self._feature_size(image_size)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        if len(images) > len(self.features):
            raise ValueError(f"the fixed feature map has {len(self.features)} rows, asked for {len(images)}")
        return self.features[: len(images)]


# ------------------------------------------------------------------------------------------ measurements
def train_step_time(net: nn.Module, loss_fn, images, rotations, grid_level: int, repeats: int) -> float:
    """Median time of one training step (forward, loss, backward, SGD step) on ``images``."""
    net.train()
    params = [p for p in net.parameters() if p.requires_grad]
    opt = torch.optim.SGD(params, lr=1e-3, momentum=0.9, nesterov=True)

    def step():
        opt.zero_grad(set_to_none=True)
        loss = loss_fn(net(images), rotations, grid_level).mean()
        loss.backward()
        opt.step()

    return median_time(step, repeats)


def eval_time(net: nn.Module, output_distribution, images, level: int, repeats: int) -> tuple[float, str]:
    """Median time per image of the level-``level`` grid evaluation (``mode()`` for point estimates)."""
    net.eval()
    with torch.no_grad():
        output = net(images)
        has_density = output_distribution(output).has_density
        if has_density:
            fn, what = (lambda: output_distribution(output).grid_logsumexp_and_max(level)), "grid"
        else:
            fn, what = (lambda: output_distribution(output).mode()), "mode()"
        seconds = median_time(fn, repeats)
    return seconds / len(images), what


def bench_method(name: str, args, tmp: Path, images, eval_images, rotations) -> dict:
    overrides = [f"model={name}", f"encoder={args.encoder}", f"dataset.image_size={args.image_size}"]
    cfg = compose_cfg(tmp, overrides)
    grid_level = int(cfg.model.train_grid_level)
    torch.manual_seed(0)
    net = instantiate(cfg.model.net)
    output_distribution, loss_fn = method_of(net)
    encoder = net.encoder
    whole = n_params(net)
    head = whole - n_params(encoder)
    r = {"method": name, "head_params": head, "whole_params": whole, "train_grid_level": grid_level}

    # 1. the head alone: the encoder replaced by its fixed output on these images
    with torch.no_grad():
        encoder.eval()
        source = images if len(eval_images) <= len(images) else torch.cat([images, eval_images])
        features = encoder(source)  # [B, C, h, w], one fixed map for both the training and eval batches
    net.encoder = FixedEncoder(features, encoder)
    r["head_train"] = train_step_time(net, loss_fn, images, rotations, grid_level, args.repeats)
    r["eval"], r["eval_kind"] = eval_time(net, output_distribution, eval_images, args.level, args.repeats)

    # 2. the whole network, the real encoder on random images
    net.encoder = encoder
    r["whole_train"] = train_step_time(net, loss_fn, images, rotations, grid_level, args.repeats)
    return r


# ------------------------------------------------------------------------------------------------ output
def fmt_int(n: int) -> str:
    return f"{n:,}"


def fmt_ratio(x: float, ref: float) -> str:
    return f"{x / ref:.2f}x" if ref > 0 else "n/a"


def print_table(results: list[dict], ref: dict, level: int) -> None:
    cols = [
        ("method", 16, "<"),
        ("head params", 13, ">"),
        ("whole params", 14, ">"),
        ("head train [ms]", 16, ">"),
        ("/ I2S", 8, ">"),
        ("whole train [ms]", 17, ">"),
        ("/ I2S", 8, ">"),
        (f"level-{level} eval [s/img]", 22, ">"),
        ("/ I2S", 8, ">"),
    ]
    print("  ".join(f"{title:{align}{w}}" for title, w, align in cols))
    for r in results:
        eval_s = f"{r['eval']:.3g}" + (" (mode)" if r["eval_kind"] != "grid" else "")
        cells = [
            r["method"],
            fmt_int(r["head_params"]),
            fmt_int(r["whole_params"]),
            f"{r['head_train'] * 1e3:.1f}",
            fmt_ratio(r["head_train"], ref["head_train"]),
            f"{r['whole_train'] * 1e3:.1f}",
            fmt_ratio(r["whole_train"], ref["whole_train"]),
            eval_s,
            fmt_ratio(r["eval"], ref["eval"]),
        ]
        print("  ".join(f"{c:{align}{w}}" for c, (_, w, align) in zip(cells, cols, strict=True)))


# -------------------------------------------------------------------------------------------------- main
def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    p.add_argument("--methods", default=",".join(METHODS), help="comma-separated conf/model names (I2S is added)")
    p.add_argument("--batch", type=int, default=32, help="images per training step")
    p.add_argument("--level", type=int, default=5, help="SO(3) HEALPix level of the evaluation")
    p.add_argument("--eval-batch", type=int, default=4, help="images per level-LEVEL evaluation")
    p.add_argument("--repeats", type=int, default=3, help="timed repeats (median) after one warm-up")
    p.add_argument("--image-size", type=int, default=224, help="image side in pixels")
    p.add_argument("--encoder", default="resnet50", help="conf/encoder option")
    p.add_argument(
        "--quick",
        action="store_true",
        help="smoke run: " + ", ".join(f"{k.replace('_', '-')} {v}" for k, v in QUICK.items()),
    )
    args = p.parse_args(argv)
    if args.quick:
        for key, value in QUICK.items():
            setattr(args, key, value)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if not (CONF / "model" / f"{m}.yaml").is_file()]
    if unknown:
        p.error(f"unknown method(s) {unknown}: options are the files of conf/model/")
    if not (CONF / "encoder" / f"{args.encoder}.yaml").is_file():
        p.error(f"unknown encoder {args.encoder!r}: options are the files of conf/encoder/")
    for key in ("batch", "eval_batch", "repeats", "image_size"):
        if getattr(args, key) < 1:
            p.error(f"--{key.replace('_', '-')} must be >= 1")
    args.methods = [REFERENCE] + [m for m in dict.fromkeys(methods) if m != REFERENCE]
    return args


def main(argv=None) -> None:
    args = parse_args(argv)
    t_start = time.perf_counter()
    print(
        f"image2sphere pose-head benchmark: {cpu_model()} ({platform.system()} {platform.machine()}, "
        f"{os.cpu_count()} cores), torch {torch.__version__}, {torch.get_num_threads()} threads, "
        f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}"
    )
    print(
        f"settings: encoder {args.encoder}, image size {args.image_size}, training batch {args.batch}, "
        f"eval level {args.level} on {args.eval_batch} image(s), float32 on CPU; "
        f"median of {args.repeats} after 1 warm-up{' (--quick)' if args.quick else ''}"
    )
    print(f"methods: {', '.join(args.methods)} (ratios: method / {REFERENCE})")
    print(load_line("at start"))

    gen = torch.Generator().manual_seed(0)
    images = torch.randn(args.batch, 3, args.image_size, args.image_size, generator=gen)
    eval_images = torch.randn(args.eval_batch, 3, args.image_size, args.image_size, generator=gen)
    rotations = random_rotations(args.batch, generator=gen)

    results = []
    with tempfile.TemporaryDirectory(prefix="heads_bench_") as tmp:
        for name in args.methods:
            t0 = time.perf_counter()
            r = bench_method(name, args, Path(tmp), images, eval_images, rotations)
            results.append(r)
            print(
                f"  {name}: head train {r['head_train'] * 1e3:.1f} ms, whole train {r['whole_train'] * 1e3:.1f} ms, "
                f"eval {r['eval']:.3g} s/image ({r['eval_kind']}) [{time.perf_counter() - t0:.0f} s]",
                flush=True,
            )
    grid_levels = sorted({r["train_grid_level"] for r in results})
    print(
        f"\nhead = every parameter but the encoder's; training step = forward + method loss (train grid level "
        f"{', '.join(map(str, grid_levels))}) + backward + SGD step, per batch of {args.batch}; "
        f"'head' with the encoder's output fixed (encoder excluded), 'whole' with {args.encoder} at "
        f"{args.image_size} px included; eval = grid_logsumexp_and_max({args.level}) per image "
        "('(mode)': point estimate, mode() only)\n"
    )
    ref = next(r for r in results if r["method"] == REFERENCE)
    print_table(results, ref, args.level)
    print(f"\ntotal benchmark time: {time.perf_counter() - t_start:.0f} s; {load_line('at end')}")


if __name__ == "__main__":
    main()
