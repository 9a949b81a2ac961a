"""Benchmark: the SO(3) ReLU, e3nn's ``SO3Activation`` against the package's ``SO3ReLU``, measured in one run.

I2S's SO(3) ReLU evaluates its signal on e3nn's SO(3) grid (``32 r^3`` rotations at resolution ``r``),
applies the ReLU there and integrates back. e3nn holds the grid's Wigner matrices densely, ``[A, B, C, n]``,
twice (input and output grid), builds them with ``wigner_D`` at every rotation, and multiplies by them.
The package's ``SO3ReLU`` computes the same numbers from the Wigner matrices written in the grid's real
Fourier basis of alpha and gamma: a sparse ``[n, B M^2]`` operator (a coefficient has one frequency in each
angle) and two small dense products per angle. Every training, evaluation and prediction process builds the
grid once per (lmax, resolution), every DDP rank included.

Printed per band limit (at its default resolution, ``max(8, lmax + 2)``), for each of the two: seconds to
build, seconds of one forward and backward pass on ``--batch`` signals (I2S's batch x channels), megabytes
of constant tensors, their ratios, and the largest difference between the two outputs (float64: e3nn's
matrices are then exact).

Usage::

    python benchmarks/relu_grid.py                   # lmax 4 and 6 (seconds)
    python benchmarks/relu_grid.py --lmax 6,8,10     # lmax 10: e3nn's constructor alone takes half a minute
"""

from __future__ import annotations

import argparse
import time

import torch
from e3nn.nn import SO3Activation

from image2sphere.nn import SO3ReLU
from image2sphere.nn.activation import _relu_grid, default_relu_resolution
from image2sphere.so3.wigner import default_dtype, n_so3_coeffs


def megabytes(module: torch.nn.Module) -> float:
    tensors = {id(t): t for t in module.buffers()}  # a tensor shared by two grids counts once
    return sum(t.numel() * t.element_size() for t in tensors.values()) / 2**20


def pass_seconds(module: torch.nn.Module, x: torch.Tensor, repeats: int = 3) -> float:
    for _ in range(repeats + 1):  # the first is a warm-up
        if _ == 1:
            start = time.perf_counter()
        x.grad = None
        module(x).square().sum().backward()
    return (time.perf_counter() - start) / repeats


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--lmax", default="4,6", help="comma-separated band limits")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float64")
    parser.add_argument("--batch", type=int, default=128, help="signals per pass (I2S: images x SO(3) channels)")
    args = parser.parse_args(argv)
    dtype = getattr(torch, args.dtype)
    print(f"# {torch.get_num_threads()} threads, torch {torch.__version__}, {args.dtype}, batch {args.batch}")
    columns = ["lmax", "res", "build e3nn", "build ours", "pass e3nn", "pass ours", "MB e3nn", "MB ours"]
    print(" ".join(f"{c:>10}" for c in columns), f"{'max |diff|':>10}")
    start = time.perf_counter()
    for lmax in (int(v) for v in args.lmax.split(",")):
        resolution = default_relu_resolution(lmax)
        t0 = time.perf_counter()
        with default_dtype(dtype):
            reference = SO3Activation(lmax, lmax, torch.relu, resolution)
            t1 = time.perf_counter()
            _relu_grid.cache_clear()
            ours = SO3ReLU(lmax, resolution)
        t2 = time.perf_counter()
        g = torch.Generator().manual_seed(0)
        x = torch.randn(args.batch, n_so3_coeffs(lmax), dtype=dtype, generator=g, requires_grad=True)
        with torch.no_grad():
            diff = float((ours(x) - reference(x)).abs().max())
        values = [t1 - t0, t2 - t1, pass_seconds(reference, x), pass_seconds(ours, x)]
        values += [megabytes(reference), megabytes(ours)]
        print(f"{lmax:>10} {resolution:>10} " + " ".join(f"{v:>10.3g}" for v in values) + f" {diff:>10.1e}")
        print(f"{'':>21} ratios e3nn / ours: build {values[0] / values[1]:.0f}x, pass {values[2] / values[3]:.1f}x, "
              f"memory {values[4] / values[5]:.0f}x")  # fmt: skip
    print(f"total benchmark time: {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
