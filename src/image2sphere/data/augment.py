"""Image augmentations that change the pose label with the image: horizontal flip and the
perspective warp of a box onto a virtual camera (PASCAL3D+, RenderForCNN).

Conventions
-----------
* Rotations ``R`` ``(..., 3, 3)`` with ``x_camera = R @ x_object`` (docs/conventions.md).
* Two camera frames appear. The *GL frame* (``x`` right, ``y`` up, ``z`` toward the viewer) is the
  frame of every rotation label in this project (the SYMSOL renderer's and PASCAL3D+'s, see
  docs/datasets.md#pascal3d-camera-frame-and-labels). The *CV frame* (``x`` right, ``y`` down, ``z``
  along the viewing direction) is the frame of pixel geometry, ``pixel ~ K @ x_cv``. They differ by
  ``GL_TO_CV = diag(1, -1, -1)``, a rotation by pi about ``x`` (its own inverse):
  ``x_cv = GL_TO_CV @ x_gl``.
* Pixel coordinates are continuous: pixel ``(row i, column j)`` covers ``[j, j+1] x [i, i+1]`` and
  its centre is ``(j + 0.5, i + 0.5)`` (Pillow's convention for geometric transforms). MATLAB-style
  1-based coordinates (PASCAL3D+ annotations), where pixel ``p`` has its centre at ``p``, are
  ``continuous = matlab - 0.5``.
* A horizontal flip mirrors the camera ``x`` axis, ``F = diag(-1, 1, 1)`` (the same in both frames).
  A flipped image of an object shows its mirror image; when the object is symmetric under the
  reflection ``M`` of its own frame (``x -> -x`` for PASCAL3D+'s left-right symmetric categories),
  the flipped image is that same object at rotation ``F @ R @ M``.
"""

from __future__ import annotations

import math

import numpy as np
from PIL import Image, ImageTransform

from image2sphere.checks import ConfigError

__all__ = [
    "GL_TO_CV",
    "MIRROR_X",
    "box_to_virtual_camera",
    "hflip_box",
    "hflip_image",
    "hflip_rotation",
    "warp_image",
]

GL_TO_CV = np.diag([1.0, -1.0, -1.0])
MIRROR_X = np.diag([-1.0, 1.0, 1.0])


def _check_matrices(R: np.ndarray, name: str) -> np.ndarray:
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise ConfigError(f"{name} must have shape (..., 3, 3), got {R.shape}")
    return R


def hflip_rotation(R: np.ndarray, mirror: np.ndarray = MIRROR_X) -> np.ndarray:
    """The rotation label of a horizontally flipped image: ``F @ R @ mirror`` ``(..., 3, 3)``.

    ``mirror`` is the object's own reflection symmetry (``diag(-1, 1, 1)`` by default). Applying
    the flip twice gives back ``R``.
    """
    R = _check_matrices(R, "R")
    mirror = _check_matrices(mirror, "mirror")
    return MIRROR_X @ R @ mirror


def hflip_image(image: np.ndarray) -> np.ndarray:
    """Mirror an image ``(..., H, W, C)`` left to right."""
    image = np.asarray(image)
    if image.ndim < 3:
        raise ConfigError(f"image must have shape (..., H, W, C), got {image.shape}")
    return image[..., ::-1, :].copy()


def hflip_box(box: np.ndarray, width: float) -> np.ndarray:
    """A box ``(x1, y1, x2, y2)`` in continuous coordinates of an image ``width`` wide, after a flip."""
    x1, y1, x2, y2 = np.asarray(box, dtype=np.float64)
    return np.array([width - x2, y1, width - x1, y2])


def box_to_virtual_camera(
    box: np.ndarray,
    K: np.ndarray,
    out_size: int,
    roll: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """The virtual camera that looks through the centre of ``box`` and sees all of it in a square image.

    The virtual camera shares the real one's centre; it is turned (rotation ``W``, CV frame) so that
    its optical axis passes through the box centre, with its ``x`` axis as close as possible to the
    real camera's ``x`` axis turned by ``roll`` (radians) about the real optical axis. Its focal
    length is chosen so that the box's four corners just fit in ``out_size x out_size``, centred
    (the aspect ratio is kept). Since only the camera turns, the image maps by the homography
    ``H = K' @ W @ K^-1`` and the object's rotation becomes ``W @ R_cv`` exactly.

    Args:
        box: ``(x1, y1, x2, y2)`` in continuous pixel coordinates of the source image.
        K: ``(3, 3)`` intrinsics of the source image.
        out_size: side of the output image in pixels.
        roll: in-plane turn of the virtual camera (radians).

    Returns:
        ``H`` ``(3, 3)``: source pixel -> output pixel (homogeneous); ``W`` ``(3, 3)``: CV-frame rotation.
    """
    x1, y1, x2, y2 = (float(v) for v in box)
    if not (x2 > x1 and y2 > y1):
        raise ConfigError(f"box must satisfy x1 < x2 and y1 < y2, got {tuple(box)}")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ConfigError(f"K must have shape (3, 3), got {K.shape}")
    K_inv = np.linalg.inv(K)
    corners = np.array([[x1, y1, 1.0], [x2, y1, 1.0], [x1, y2, 1.0], [x2, y2, 1.0]]).T  # [3, 4]
    rays = K_inv @ corners  # [3, 4] camera-frame directions of the corners
    centre = K_inv @ np.array([(x1 + x2) / 2, (y1 + y2) / 2, 1.0])
    z = centre / np.linalg.norm(centre)
    up = np.array([math.cos(roll), math.sin(roll), 0.0])  # the real x axis, turned by roll
    x = up - (up @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    W = np.stack([x, y, z])  # rows: the virtual camera's axes in the real camera frame
    seen = W @ rays  # [3, 4]
    extent = np.abs(seen[:2] / seen[2]).max()
    f = (out_size / 2) / extent
    K_new = np.array([[f, 0.0, out_size / 2], [0.0, f, out_size / 2], [0.0, 0.0, 1.0]])
    return K_new @ W @ K_inv, W


def warp_image(image: Image.Image, H: np.ndarray, out_size: int) -> np.ndarray:
    """Resample ``image`` through the homography ``H`` (source -> output pixels): uint8 ``(S, S, 3)``.

    Bilinear; output pixels that see nothing of the source are black. When the output samples the
    source more than twice as sparsely (a large box), the source is first reduced by an integer
    factor with a box filter, so that the result is not aliased.
    """
    H = np.asarray(H, dtype=np.float64)
    # output pixels per source pixel near the output centre (the local scale of the homography)
    c = np.linalg.solve(H, np.array([out_size / 2, out_size / 2, 1.0]))
    c = c / c[2]
    step = H @ np.stack([c + [1.0, 0.0, 0.0], c + [0.0, 1.0, 0.0]], axis=1)
    mapped = step[:2] / step[2] - out_size / 2
    scale = float(np.linalg.norm(mapped, axis=0).max())
    factor = int(1.0 / scale) if scale > 0 else 1
    if factor >= 2:
        image = image.reduce(factor)
        H = H @ np.diag([float(factor), float(factor), 1.0])  # reduced pixel x/factor is source pixel x
    H_inv = np.linalg.inv(H)
    H_inv /= H_inv[2, 2]
    # fill=1: output pixels that see nothing of the source are set to zero (black)
    warped = image.transform(
        (out_size, out_size),
        ImageTransform.PerspectiveTransform(tuple(H_inv.reshape(-1)[:8])),
        resample=Image.Resampling.BILINEAR,
        fill=1,
    )
    return np.asarray(warped, dtype=np.uint8).copy()
