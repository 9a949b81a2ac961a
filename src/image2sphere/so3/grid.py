"""HEALPix grids on S2 and SO(3), and near-identity kernel grids.

Conventions (docs/conventions.md#so3-healpix-grid)
--------------------------------------------------
* S2 points are given as YXY angles ``(alpha, beta)``: the point is ``R(alpha, beta, 0) @ e_y =
  (sin b sin a, cos b, sin b cos a)`` (e3nn's ``angles_to_xyz``). HEALPix pixel ``p`` of
  ``nside = 2**level`` in RING order has ``beta, alpha = healpy.pix2ang(nside, p)``; the map
  ``(theta, phi) -> (beta, alpha)`` is an isometry, so HEALPix distances carry over.
* SO(3) HEALPix grid of level r: pixels ``p`` as above, ``gamma_k = 2 pi k / (6 nside)`` for
  ``k = 0 .. 6 nside - 1``; rotation ``R(alpha_p, beta_p, gamma_k)``.
* **Flat order of the SO(3) grid is pixel-major: index = p * n_gamma + k.** Every function of this
  package that returns grid values or grid indices uses this order. (The original research code
  is gamma-major, ``k * npix + p``; :func:`gamma_major_to_pixel_major` converts indices.)
* Grid size ``72 * 8**level``; the grid is equivolumetric: equal-area pixels times a uniform
  gamma fibre.
"""

from __future__ import annotations

import math
import numbers

import healpy
import numpy as np
import torch

from image2sphere.checks import ConfigError, check_int
from image2sphere.so3.rotations import angles_to_matrix, check_rotation_matrix, rotvec_to_matrix

__all__ = [
    "check_grid_levels",
    "MAX_DENSE_LEVEL",
    "MAX_LEVEL",
    "MAX_STREAMED_LEVEL",
    "check_grid_index",
    "check_level",
    "gamma_major_to_pixel_major",
    "s2_healpix_grid",
    "so3_grid_size",
    "so3_healpix_grid",
    "so3_healpix_grid_angles",
    "so3_healpix_index_to_angles",
    "so3_healpix_index_to_matrix",
    "so3_healpix_nearest_index",
    "so3_near_identity_grid",
    "so3_tube_grid",
]

MAX_LEVEL = 10  # nside 1024: 7.7e10 rotations; the ceiling of index arithmetic (sizes, index <-> rotation)
MAX_STREAMED_LEVEL = 7  # streamed evaluation on the grid (151M points; operator 0.68 GB for lmax 6)
MAX_DENSE_LEVEL = 6  # anything holding one value or matrix per grid point (18.9M points)


def _format_bytes(nbytes: float) -> str:
    for unit, size in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if nbytes >= size:
            return f"{nbytes / size:.3g} {unit}"
    return f"{nbytes:.0f} bytes"


def check_level(
    level,
    name: str = "level",
    max_level: int = MAX_LEVEL,
    purpose: str | None = None,
    bytes_per_point: float = 0.0,
) -> int:
    """Return ``level`` as an int, or raise ``ValueError`` unless it is an integer in ``0..max_level``.

    Every public function that takes a grid level calls this first, before it allocates or builds
    anything, with the finest level its work allows: :data:`MAX_LEVEL` for index arithmetic,
    :data:`MAX_STREAMED_LEVEL` for streamed evaluation, :data:`MAX_DENSE_LEVEL` for anything that
    holds one value per grid point. A level that is too fine is refused with the size of its grid
    (``72 * 8**level`` points, times ``bytes_per_point`` bytes) and the levels ``purpose`` allows.
    """
    if isinstance(level, bool) or not isinstance(level, numbers.Integral) or level < 0:
        raise ConfigError(f"{name} must be an integer in 0..{max_level}, got {level!r}")
    level = int(level)
    if level > max_level:
        detail = f" for {purpose}" if purpose else ""
        if purpose and level <= 30:  # the size of what would have been built (beyond 30 it says nothing more)
            n_points = 72 * 8**level
            cost = (
                f", {_format_bytes(n_points * bytes_per_point)} at {bytes_per_point:g} bytes each"
                if bytes_per_point
                else ""
            )
            detail += f": its SO(3) grid has {n_points:,} points{cost}"
            detail += f"; the allowed levels are 0..{max_level} (level {max_level}: {72 * 8**max_level:,} points)"
        else:
            detail += f"; the allowed levels are 0..{max_level}"
        raise ConfigError(f"{name}={level} is too fine{detail}")
    return level


def check_grid_levels(prefix: str = "model.", **levels: int) -> None:
    """Refuse the grid levels of a training or evaluation run that it could not evaluate on, naming each key
    (``prefix`` + the keyword): a ``*spread_grid_level`` up to :data:`MAX_DENSE_LEVEL` (the spread sums one
    value per grid point), every other level up to :data:`MAX_STREAMED_LEVEL` (streamed evaluation).

    Called by :class:`~image2sphere.training.module.PoseEstimationModule` and, before any data is read or
    rendered, by the training run's config check (:func:`image2sphere.training.run_config.check_train_config`).
    """
    for key, level in levels.items():
        if key.endswith("spread_grid_level"):
            check_level(level, name=f"{prefix}{key}", max_level=MAX_DENSE_LEVEL, purpose="the spread's dense grid")
        else:
            check_level(level, name=f"{prefix}{key}", max_level=MAX_STREAMED_LEVEL, purpose="streamed evaluation")


def so3_grid_size(level: int) -> tuple[int, int]:
    """``(n_pixels, n_gamma)`` of the SO(3) grid: ``12 * 4**level`` and ``6 * 2**level``."""
    nside = 2 ** check_level(level)
    return 12 * nside * nside, 6 * nside


def s2_healpix_grid(
    level: int, max_beta: float = math.pi, dtype: torch.dtype = torch.float32
) -> tuple[torch.Tensor, torch.Tensor]:
    """HEALPix pixel centres (RING order) of ``nside = 2**level`` as ``(alpha, beta)``, each ``(P,)``.

    ``max_beta < pi`` keeps only the cap ``beta <= max_beta`` around ``+y`` (e.g. ``pi / 2`` for
    the hemisphere the image is projected onto).
    """
    nside = 2 ** check_level(level)
    if not 0 < max_beta <= math.pi:
        raise ConfigError(f"max_beta must be in (0, pi], got {max_beta!r}")
    beta, alpha = healpy.pix2ang(nside, np.arange(healpy.nside2npix(nside)), nest=False)
    keep = beta <= max_beta + 1e-12
    return torch.as_tensor(alpha[keep], dtype=dtype), torch.as_tensor(beta[keep], dtype=dtype)


def so3_healpix_grid_angles(
    level: int, dtype: torch.dtype = torch.float32
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """YXY angles ``(alpha, beta, gamma)`` of the SO(3) grid, each ``(N,)``, pixel-major order.

    Levels up to :data:`MAX_DENSE_LEVEL` (the angles are built in float64).
    """
    check_level(level, max_level=MAX_DENSE_LEVEL, purpose="the dense grid of angles", bytes_per_point=24)
    n_pix, n_gamma = so3_grid_size(level)
    alpha, beta = s2_healpix_grid(level, dtype=torch.float64)
    gamma = torch.arange(n_gamma, dtype=torch.float64) * (2 * math.pi / n_gamma)
    alpha = alpha[:, None].expand(n_pix, n_gamma).reshape(-1)  # [N]
    beta = beta[:, None].expand(n_pix, n_gamma).reshape(-1)  # [N]
    gamma = gamma[None, :].expand(n_pix, n_gamma).reshape(-1)  # [N]
    return alpha.to(dtype), beta.to(dtype), gamma.to(dtype)


def so3_healpix_grid(level: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Rotations ``(72 * 8**level, 3, 3)`` of the SO(3) HEALPix grid, pixel-major order.

    Levels up to :data:`MAX_DENSE_LEVEL` (level 6: 1.4 GB of float64 matrices while they are built);
    finer grids are only ever evaluated streamed (:mod:`image2sphere.so3.grid_eval`).
    """
    check_level(level, max_level=MAX_DENSE_LEVEL, purpose="a dense grid of rotation matrices", bytes_per_point=72)
    alpha, beta, gamma = so3_healpix_grid_angles(level, dtype=torch.float64)
    return angles_to_matrix(alpha, beta, gamma).to(dtype)


def check_grid_index(index, level: int) -> torch.Tensor:
    """``index`` as a tensor, or ``ValueError`` unless all are integers in ``[0, 72 * 8**level)``."""
    n_points = math.prod(so3_grid_size(level))
    index = torch.as_tensor(index)
    if index.is_floating_point() or index.dtype == torch.bool or ((index < 0) | (index >= n_points)).any():
        raise ConfigError(f"grid indices must be integers in [0, {n_points}) for level {level}")
    return index


def gamma_major_to_pixel_major(index: torch.Tensor, level: int) -> torch.Tensor:
    """Convert grid indices of the original code's order (``k * npix + p``) to ours (``p * ngamma + k``)."""
    n_pix, n_gamma = so3_grid_size(level)
    index = check_grid_index(index, level)
    k, p = index // n_pix, index % n_pix
    return p * n_gamma + k


def so3_near_identity_grid(
    max_angle: float = math.pi / 8,
    axis_level: int = 1,
    n_angles: int = 3,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Rotations ``(1 + 12 * 4**axis_level * n_angles, 3, 3)`` within ``max_angle`` of the identity.

    The identity, plus rotations about every HEALPix axis of level ``axis_level`` (full sphere) by
    the angles ``max_angle * k / n_angles``, ``k = 1..n_angles``. Used as the support of locally
    supported SO(3) filters (22.5 degrees in the paper).
    """
    check_level(axis_level, "axis_level", max_level=MAX_DENSE_LEVEL)
    if not 0 < max_angle <= math.pi:
        raise ConfigError(f"max_angle must be in (0, pi], got {max_angle!r}")
    check_int("n_angles", n_angles, 1)
    alpha, beta = s2_healpix_grid(axis_level, dtype=torch.float64)
    axes = torch.stack(  # [A, 3], e3nn's angles_to_xyz
        [torch.sin(beta) * torch.sin(alpha), torch.cos(beta), torch.sin(beta) * torch.cos(alpha)], dim=-1
    )
    angles = torch.arange(1, n_angles + 1, dtype=torch.float64) * (max_angle / n_angles)  # [K]
    rotvec = (axes[:, None, :] * angles[None, :, None]).reshape(-1, 3)  # [A*K, 3]
    rotvec = torch.cat([torch.zeros(1, 3, dtype=torch.float64), rotvec])
    return rotvec_to_matrix(rotvec).to(dtype)


def so3_tube_grid(
    max_beta: float = math.pi / 8,
    n_alpha: int = 7,
    n_beta: int = 3,
    n_gamma: int = 8,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Rotations ``(n_alpha * n_beta * n_gamma, 3, 3)`` that tilt the ``y`` axis by at most ``max_beta``.

    YXY angles ``(a, b, g - a)`` for ``a = 2 pi j / n_alpha``, ``b = max_beta k / n_beta``
    (``k = 1..n_beta``) and ``g`` evenly spaced over ``[-2 pi, 2 pi]`` (both ends included). The
    turn about ``y`` is unrestricted, so this is a tube around the subgroup of rotations about
    ``y``, not a neighbourhood of the identity: with the defaults 168 rotations, of which only the
    42 with ``g = +-2 pi`` lie within ``max_beta`` of the identity. It is the kernel grid of the
    original I2S research code, offered for comparison (``I2S(so3_kernel="tube")``).
    """
    if not 0 < max_beta <= math.pi:
        raise ConfigError(f"max_beta must be in (0, pi], got {max_beta!r}")
    for name, n in (("n_alpha", n_alpha), ("n_beta", n_beta), ("n_gamma", n_gamma)):
        check_int(name, n, 1)
    a = torch.arange(n_alpha, dtype=torch.float64) * (2 * math.pi / n_alpha)
    b = torch.arange(1, n_beta + 1, dtype=torch.float64) * (max_beta / n_beta)
    g = torch.linspace(-2 * math.pi, 2 * math.pi, n_gamma, dtype=torch.float64)
    A, B, G = torch.meshgrid(a, b, g, indexing="ij")
    return angles_to_matrix(A.reshape(-1), B.reshape(-1), (G - A).reshape(-1)).to(dtype)


def so3_healpix_index_to_angles(index: torch.Tensor, level: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """YXY angles of grid points given by flat (pixel-major) indices of any shape."""
    n_pix, n_gamma = so3_grid_size(level)
    index = check_grid_index(index, level)
    pix = (index // n_gamma).cpu().numpy()
    beta, alpha = healpy.pix2ang(2**level, pix.reshape(-1), nest=False)
    alpha = torch.as_tensor(alpha, dtype=torch.float64).reshape(index.shape)
    beta = torch.as_tensor(beta, dtype=torch.float64).reshape(index.shape)
    gamma = (index % n_gamma).cpu().to(torch.float64) * (2 * math.pi / n_gamma)
    return alpha, beta, gamma


def so3_healpix_index_to_matrix(index: torch.Tensor, level: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Rotations ``(..., 3, 3)`` of grid points given by flat (pixel-major) indices ``(...)``."""
    index = torch.as_tensor(index)
    return angles_to_matrix(*so3_healpix_index_to_angles(index, level)).to(dtype=dtype, device=index.device)


_pixel_frames: dict[int, torch.Tensor] = {}


def _pixel_frame_matrices(level: int) -> torch.Tensor:
    """``R(alpha_p, beta_p, 0)`` for every pixel, ``(P, 3, 3)`` float64, cached per level."""
    if level not in _pixel_frames:
        alpha, beta = s2_healpix_grid(level, dtype=torch.float64)
        _pixel_frames[level] = angles_to_matrix(alpha, beta, torch.zeros_like(alpha))
    return _pixel_frames[level]


def so3_healpix_nearest_index(rotations: torch.Tensor, level: int, chunk_size: int = 16384) -> torch.Tensor:
    """Flat (pixel-major) index ``(...)`` of the grid point geodesically nearest each rotation ``(..., 3, 3)``.

    No dense search: the S2 point ``u = R e_y`` of the nearest grid rotation lies within the grid's
    covering radius of ``R e_y`` (``angle(R e_y, R' e_y) <= angle(R, R')``), so the candidates are
    the HEALPix pixel containing ``u`` and two rings of neighbours around it. For each candidate
    pixel the best gamma is found in closed form (the trace is a sinusoid in gamma), and the two
    grid gammas around it are scored. Tests compare against a brute-force search.
    """
    nside = 2 ** check_level(level)  # first: nothing is built for a bad level
    check_rotation_matrix(rotations)
    n_pix, n_gamma = so3_grid_size(level)
    frames = _pixel_frame_matrices(level)  # [P, 3, 3]
    batch_shape = rotations.shape[:-2]
    R_all = rotations.detach().reshape(-1, 3, 3).to(device="cpu", dtype=torch.float64)
    out = torch.empty(R_all.shape[0], dtype=torch.long)
    step = 2 * math.pi / n_gamma
    for start in range(0, R_all.shape[0], chunk_size):
        R = R_all[start : start + chunk_size]  # [M, 3, 3]
        u = R[:, :, 1].numpy()  # R e_y, [M, 3]
        p0 = healpy.vec2pix(nside, u[:, 2], u[:, 0], u[:, 1], nest=False)  # healpy (x, y, z) = (u_z, u_x, u_y)
        ring1 = healpy.get_all_neighbours(nside, p0, nest=False)  # [8, M], -1 where missing
        ring1 = np.where(ring1 < 0, p0[None], ring1)
        ring2 = healpy.get_all_neighbours(nside, ring1.reshape(-1), nest=False).reshape(64, -1)
        ring2 = np.where(ring2 < 0, p0[None], ring2)
        cand = torch.as_tensor(np.concatenate([p0[None], ring1, ring2]).T)  # [M, C]
        A = frames[cand]  # [M, C, 3, 3]
        Mx = torch.einsum("mji,mcjk->mcik", R, A)  # R^T A  [M, C, 3, 3]
        s = Mx[..., 0, 0] + Mx[..., 2, 2]  # [M, C]
        t = Mx[..., 2, 0] - Mx[..., 0, 2]  # [M, C]
        g_best = torch.atan2(t, s) % (2 * math.pi)  # [M, C]
        k0 = torch.floor(g_best / step).long() % n_gamma
        ks = torch.stack([k0, (k0 + 1) % n_gamma], dim=-1)  # [M, C, 2]
        g = ks.to(torch.float64) * step
        trace = s[..., None] * torch.cos(g) + t[..., None] * torch.sin(g) + Mx[..., 1, 1, None]  # [M, C, 2]
        best = trace.reshape(trace.shape[0], -1).argmax(dim=1)  # [M]
        rows = torch.arange(trace.shape[0])
        pix = cand[rows, best // 2]
        k = ks.reshape(trace.shape[0], -1)[rows, best]
        out[start : start + chunk_size] = pix * n_gamma + k
    return out.reshape(batch_shape).to(rotations.device)
