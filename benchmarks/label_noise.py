"""Measurement: how long I2S waits at uniform on a symmetric shape, with one random equivalent label per
image (the paper's training, ``dataset.label=random``) or with the loss averaged over every equivalent
label (``dataset.label=all``).

At the uniform start the loss's gradient with respect to the output's Fourier coefficients is the
label's flat Wigner vector. Averaged over the image's equivalent rotations only the rows invariant
under the shape's symmetry group survive; the rest is zero-mean noise of the draw. For the
icosahedron that leaves degree 6 alone, 2.9 % of the gradient's energy (cube 4.8 %, tetrahedron 9.3 %;
tests/test_band_limit_training.py). This script trains the default I2S (ResNet-18 from random
initialisation, Adam at lr 1e-3, batches of 32) on rendered images of one shape, the same seed and
batches in both modes, and prints every 25 steps the training loss averaged over each image's
equivalent set (the quantity both modes minimise in expectation; uniform: ``log N`` of the level-3
grid, 10.51) and the RMS of the output's coefficients per degree. docs/training_fidelity.md ("Every
SYMSOL shape") has the results.

Usage::

    python benchmarks/label_noise.py                         # icosa, 200 steps, seed 0, both modes
    python benchmarks/label_noise.py --shape cube --steps 100
"""

from __future__ import annotations

import argparse
import math
import time

import torch

from image2sphere.data.common import normalize_images
from image2sphere.data.raycast import render
from image2sphere.data.symmetry import symmetry_group
from image2sphere.nn import I2S, ResNetEncoder
from image2sphere.so3 import random_rotations
from image2sphere.so3.grid import so3_healpix_nearest_index
from image2sphere.so3.grid_eval import get_grid_evaluator
from image2sphere.so3.wigner import so3_blocks

LEVEL = 3  # the training grid


def run(shape: str, mode: str, steps: int, seed: int, n_images: int, image_size: int) -> list[tuple]:
    """``(step, set loss, output RMS per degree)`` every 25 steps of one training run."""
    g = torch.Generator().manual_seed(1000 + seed)  # the data: the same in both modes
    rotations = random_rotations(n_images, generator=g, dtype=torch.float32)  # [N, 3, 3]
    images = normalize_images(render(shape, rotations, image_size=image_size))  # [N, 3, S, S]
    G = symmetry_group(shape).to(torch.float32)  # [|G|, 3, 3]: x_camera = R x_object, so R g is equivalent
    index = so3_healpix_nearest_index((rotations[:, None] @ G[None]).reshape(-1, 3, 3), LEVEL).view(n_images, -1)
    torch.manual_seed(seed)
    net = I2S(ResNetEncoder(depth=18), image_size=image_size, lmax=6)
    ev = get_grid_evaluator(6, LEVEL, torch.float32, torch.device("cpu"))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    order = torch.Generator().manual_seed(seed)
    draw = torch.Generator().manual_seed(seed + 1)
    log = []
    for step in range(steps):
        batch = torch.randint(n_images, (32,), generator=order)
        coeffs = net(images[batch])  # [32, n_so3]
        values = ev.logits_at(coeffs, index[batch])  # [32, |G|]
        lse = ev.logsumexp(coeffs)  # [32]
        set_loss = lse - values.mean(1)
        if mode == "random":
            pick = torch.randint(values.shape[1], (32,), generator=draw)
            loss = (lse - values.gather(1, pick[:, None])[:, 0]).mean()
        else:
            loss = set_loss.mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step % 25 == 0 or step == steps - 1:
            rms = [float(coeffs[:, b].detach().pow(2).mean().sqrt()) for _, b in so3_blocks(6)]
            log.append((step, float(set_loss.mean()), rms))
    return log


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shape", default="icosa", help="a shape of the renderer with a finite group")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--images", type=int, default=2048, help="rendered training images")
    parser.add_argument("--image-size", type=int, default=96)
    args = parser.parse_args()
    uniform = math.log(get_grid_evaluator(6, LEVEL, torch.float32, torch.device("cpu")).n_points)
    print(f"{args.shape}, {args.images} images at {args.image_size} px, seed {args.seed}; uniform: {uniform:.3f}")
    for mode in ("random", "all"):
        start = time.time()
        for step, loss, rms in run(args.shape, mode, args.steps, args.seed, args.images, args.image_size):
            degrees = " ".join(f"{r:.4f}" for r in rms)
            print(f"label={mode:6s} step {step:4d}  set loss {loss:6.3f}  output RMS per degree 0..6: {degrees}")
        print(f"label={mode}: {time.time() - start:.0f} s")


if __name__ == "__main__":
    main()
