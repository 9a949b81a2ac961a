"""Rotation math, HEALPix grids on S2 and SO(3), Wigner layouts and SO(3) distributions.

Conventions are fixed project-wide (see ``SPEC.md`` section 1 and each module's docstring):
column-vector rotation matrices, e3nn YXY Euler angles, the flat Wigner layout for SO(3) signals,
and a pixel-major flat order (``p * n_gamma + k``) for the SO(3) HEALPix grid.
"""

from image2sphere.so3.distribution import LOG_UNIFORM_DENSITY, SO3Distribution
from image2sphere.so3.grid import (
    MAX_LEVEL,
    check_grid_index,
    check_level,
    gamma_major_to_pixel_major,
    s2_healpix_grid,
    so3_grid_size,
    so3_healpix_grid,
    so3_healpix_grid_angles,
    so3_healpix_index_to_angles,
    so3_healpix_index_to_matrix,
    so3_healpix_nearest_index,
    so3_near_identity_grid,
)
from image2sphere.so3.grid_eval import HealpixGridEvaluator, dense_grid_logits, get_grid_evaluator
from image2sphere.so3.rotations import (
    angles_to_matrix,
    check_rotation_matrix,
    geodesic_distance,
    geodesic_distance_deg,
    matrix_to_angles,
    project_to_so3,
    quaternion_to_matrix,
    random_rotations,
    rotvec_to_matrix,
)
from image2sphere.so3.wigner import (
    check_lmax,
    flat_wigner,
    flat_wigner_from_angles,
    left_translate_so3_coeffs,
    lmax_from_n_so3_coeffs,
    n_s2_coeffs,
    n_so3_coeffs,
    rotate_s2_coeffs,
    so3_blocks,
    so3_layout,
    wigner_D,
)

__all__ = [
    "LOG_UNIFORM_DENSITY",
    "MAX_LEVEL",
    "HealpixGridEvaluator",
    "SO3Distribution",
    "angles_to_matrix",
    "check_grid_index",
    "check_level",
    "check_lmax",
    "check_rotation_matrix",
    "dense_grid_logits",
    "flat_wigner",
    "flat_wigner_from_angles",
    "gamma_major_to_pixel_major",
    "geodesic_distance",
    "geodesic_distance_deg",
    "get_grid_evaluator",
    "left_translate_so3_coeffs",
    "lmax_from_n_so3_coeffs",
    "matrix_to_angles",
    "n_s2_coeffs",
    "n_so3_coeffs",
    "project_to_so3",
    "quaternion_to_matrix",
    "random_rotations",
    "rotate_s2_coeffs",
    "rotvec_to_matrix",
    "s2_healpix_grid",
    "so3_blocks",
    "so3_grid_size",
    "so3_healpix_grid",
    "so3_healpix_grid_angles",
    "so3_healpix_index_to_angles",
    "so3_healpix_index_to_matrix",
    "so3_healpix_nearest_index",
    "so3_layout",
    "so3_near_identity_grid",
    "wigner_D",
]
