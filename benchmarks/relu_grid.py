"""Benchmark: building the SO(3) ReLU's grid, e3nn's constructor against the package's, measured in one run.

I2S's SO(3) ReLU (``image2sphere.nn.SO3ReLU``) evaluates its signal on e3nn's SO(3) grid. e3nn's
``SO3Activation(lmax, lmax, relu, resolution)`` builds the grid's Wigner matrices with ``wigner_D`` at every
one of its ``32 resolution^3`` rotations, once for its input grid and once for its output grid. The package
builds the same module at degree 0 and fills both grids with one tensor from
``image2sphere.so3.flat_wigner_on_euler_grid`` (each angle's matrices, composed). Every training, evaluation
and prediction process pays this once per (lmax, resolution) at start-up, every DDP rank included.

Printed per band limit (at its default resolution, ``max(8, lmax + 2)``): seconds for each, their ratio, the
largest difference between the two ReLUs' outputs on random signals (float64, where e3nn's matrices are
exact), and the megabytes of Wigner matrices each keeps.

Usage::

    python benchmarks/relu_grid.py                   # lmax 4 and 6 (under a minute)
    python benchmarks/relu_grid.py --lmax 6,8,10     # lmax 10: e3nn's constructor alone takes minutes
"""

from __future__ import annotations

import argparse
import time

import torch
from e3nn.nn import SO3Activation

from image2sphere.nn.activation import _relu_on_grid, default_relu_resolution
from image2sphere.so3.wigner import default_dtype, n_so3_coeffs


def megabytes(act: SO3Activation) -> float:
    tensors = {id(t): t for t in (act.grid_in.D, act.grid_out.D)}  # one tensor when the grids share it
    return sum(t.numel() * t.element_size() for t in tensors.values()) / 2**20


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--lmax", default="4,6", help="comma-separated band limits")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float64")
    args = parser.parse_args(argv)
    dtype = getattr(torch, args.dtype)
    print(f"# {torch.get_num_threads()} threads, torch {torch.__version__}, {args.dtype}")
    header = ("lmax", 4), ("res", 4), ("e3nn s", 8), ("ours s", 8), ("ratio", 7), ("max |diff|", 11), ("e3nn MB", 8)
    print(" ".join(f"{name:>{width}}" for name, width in header), f"{'ours MB':>8}")
    start = time.perf_counter()
    for lmax in (int(v) for v in args.lmax.split(",")):
        resolution = default_relu_resolution(lmax)
        t0 = time.perf_counter()
        with default_dtype(dtype):
            reference = SO3Activation(lmax, lmax, torch.relu, resolution)
        t1 = time.perf_counter()
        _relu_on_grid.cache_clear()
        ours = _relu_on_grid(lmax, resolution, dtype)
        t2 = time.perf_counter()
        x = torch.randn(16, n_so3_coeffs(lmax), dtype=dtype, generator=torch.Generator().manual_seed(0))
        with torch.no_grad():
            diff = float((ours(x) - reference(x)).abs().max())
        e3nn_s, ours_s = t1 - t0, t2 - t1
        print(f"{lmax:>4} {resolution:>4} {e3nn_s:>8.2f} {ours_s:>8.2f} {e3nn_s / ours_s:>6.1f}x {diff:>11.1e} "
              f"{megabytes(reference):>8.0f} {megabytes(ours):>8.0f}")  # fmt: skip
    print(f"total benchmark time: {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
