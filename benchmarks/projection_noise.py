"""Measurement: how much of the projection's Fourier coefficients is sampling noise, per degree.

I2S projects the image's feature map onto HEALPix points of a hemisphere and takes the spherical
harmonic coefficients of that point signal, ``mean_i f(u_i) Y(u_i)``. The paper uses a random subset
of 20 of the 104 points per training pass (``model.net.n_subset=20``); at test, and by default in
training, every point is used. The subset's coefficients are an unbiased estimate of the all-points
ones, with a sampling noise that this script measures against the signal, per degree l:

    ratio_l = E |x_subset^l - x_all^l|^2 / E |x_all^l|^2

over rendered cube and cone images (the built-in data's shapes), an untrained I2S (ResNet-18, random
initialisation, seed 0) and ``--draws`` random subsets per image. Above 1 the subset's degree-l
coefficients are more noise than signal. docs/training_fidelity.md ("The band limit") explains why
this stopped I2S from learning at lmax 8 and 10.

Usage::

    python benchmarks/projection_noise.py                       # 96 px (3x3 feature map) and 224 px (7x7)
    python benchmarks/projection_noise.py --image-sizes 96 --lmax 8 --draws 8
"""

from __future__ import annotations

import argparse
import time

import torch

from image2sphere.data.common import normalize_images
from image2sphere.data.raycast import render
from image2sphere.nn import I2S, ResNetEncoder
from image2sphere.so3 import random_rotations


def noise_to_signal(image_size: int, lmax: int, subset: int, draws: int, images_per_shape: int) -> list[float]:
    """``ratio_l`` for l = 0..lmax (see the module docstring)."""
    g = torch.Generator().manual_seed(0)
    images = torch.cat(
        [
            normalize_images(render(shape, random_rotations(images_per_shape, generator=g), image_size=image_size))
            for shape in ("cube", "cone")
        ]
    )  # [B, 3, H, W]
    torch.manual_seed(0)
    net = I2S(ResNetEncoder(depth=18, weights=None), image_size=image_size, lmax=lmax, n_subset=subset).eval()
    projector = net.projector
    torch.manual_seed(0)  # the subsets the projector draws in training mode
    with torch.no_grad():
        features = net.features(images, None)
        exact = projector.eval()(features)  # [B, S, (L+1)^2] on every point
        noise = torch.stack([projector.train()(features) - exact for _ in range(draws)])  # [draws, B, S, (L+1)^2]
    ratios = []
    for l in range(lmax + 1):
        band = slice(l * l, (l + 1) ** 2)
        ratios.append(float(noise[..., band].pow(2).mean() / exact[..., band].pow(2).mean()))
    return ratios


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--image-sizes", type=int, nargs="+", default=[96, 224])
    parser.add_argument("--lmax", type=int, default=10)
    parser.add_argument("--subset", type=int, default=20, help="projection points per training pass (the paper: 20)")
    parser.add_argument("--draws", type=int, default=32, help="random subsets per image")
    parser.add_argument("--images", type=int, default=8, help="images per shape")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    table = {size: noise_to_signal(size, args.lmax, args.subset, args.draws, args.images) for size in args.image_sizes}
    print(f"noise / signal of the projection's coefficients on {args.subset} random points, per degree l")
    print("l    " + "".join(f"{f'{size} px':>10}" for size in args.image_sizes))
    for l in range(args.lmax + 1):
        print(f"{l:<5}" + "".join(f"{table[size][l]:10.2f}" for size in args.image_sizes))
    print(f"measured in {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
