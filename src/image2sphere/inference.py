"""Distributions over SO(3) for your own images from a trained checkpoint.

>>> predictor = Predictor.from_checkpoint("logs/train/runs/<run>/checkpoints/last.ckpt")
>>> dist = predictor(["mug.jpg", "mug2.png"])            # SO3Distribution, batch of 2
>>> modes = dist.modes(level=5, k=5)                      # [(rotations (k, 3, 3), mass (k,)), ...]

Preprocessing is the one the model was trained with: RGB, resized to the run's
``dataset.image_size`` (bilinear), ImageNet normalisation. Images are expected to be framed as the
training images were (e.g. for PASCAL3D+: the object's box, warped or cropped to a square).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from image2sphere.data.common import image_to_uint8, load_image, normalize_images
from image2sphere.so3.distribution import SO3Distribution
from image2sphere.so3.rotations import matrix_to_angles
from image2sphere.training.checkpoint import build_module, load_checkpoint

__all__ = ["Predictor", "format_modes", "predict"]

log = logging.getLogger(__name__)

ImageLike = str | Path | Image.Image | np.ndarray | torch.Tensor


class Predictor:
    """A trained pose network with its preprocessing; call it on images to get distributions.

    Args:
        net: the network (``lmax``, ``num_classes``, ``forward(images[, class_index])``).
        image_size: the square input size it was trained with.
        class_names: names of the class indices (for models with class-label input).
        device: where the network runs.
    """

    def __init__(self, net: torch.nn.Module, image_size: int, class_names: Sequence[str] | None = None,
                 device: str | torch.device = "cpu"):  # fmt: skip
        self.device = torch.device(device)
        self.net = net.to(self.device).eval()
        self.image_size = int(image_size)
        self.class_names = list(class_names) if class_names else None
        self.lmax = net.lmax

    @classmethod
    def from_checkpoint(cls, path: str | Path, device: str | torch.device = "cpu") -> Predictor:
        """Load a checkpoint of ``python -m src.train`` (``weights_only=True``; see
        :mod:`image2sphere.training.checkpoint`)."""
        ckpt = load_checkpoint(path)
        module = build_module(ckpt, path)
        image_size = ckpt["run_config"].get("dataset", {}).get("image_size") or module.net.image_size
        return cls(module.net, int(image_size), module.class_names, device)

    def preprocess(self, images: ImageLike | Sequence[ImageLike]) -> torch.Tensor:
        """Images (paths, PIL images, uint8 arrays ``(H, W, 3)``) -> normalised ``(B, 3, S, S)``."""
        if isinstance(images, (str, Path, Image.Image)) or (
            isinstance(images, (np.ndarray, torch.Tensor)) and images.ndim == 3
        ):
            images = [images]
        batch = []
        for image in images:
            if isinstance(image, (str, Path)):
                pixels = load_image(image, self.image_size)
            else:
                if isinstance(image, (np.ndarray, torch.Tensor)):
                    array = np.asarray(image)
                    if array.ndim != 3 or array.shape[-1] != 3 or array.dtype != np.uint8:
                        raise ValueError(
                            f"image arrays must be uint8 of shape (H, W, 3), got {array.dtype} {array.shape}"
                        )
                    image = Image.fromarray(array)
                pixels = image_to_uint8(image, self.image_size)
            batch.append(normalize_images(pixels))
        if not batch:
            raise ValueError("no images given")
        return torch.stack(batch).to(self.device)

    @torch.no_grad()
    def __call__(self, images: ImageLike | Sequence[ImageLike], class_index=None) -> SO3Distribution:
        """The predicted distribution for each image (batch in the order given)."""
        x = self.preprocess(images)
        if getattr(self.net, "num_classes", 0):
            if class_index is None:
                names = (
                    f" ({', '.join(f'{i}={n}' for i, n in enumerate(self.class_names))})" if self.class_names else ""
                )
                raise ValueError(f"this model takes the object class as input: pass class_index{names}")
            class_index = torch.as_tensor(class_index, device=self.device).reshape(-1).expand(len(x))
            coeffs = self.net(x, class_index)
        else:
            coeffs = self.net(x)
        return SO3Distribution(coeffs, self.lmax)


def format_modes(rotations: torch.Tensor, mass: torch.Tensor) -> str:
    """The modes as text: probability mass, YXY angles (degrees) and the matrix of each."""
    alpha, beta, gamma = (np.degrees(a.double().numpy()) for a in matrix_to_angles(rotations.double()))
    lines = []
    for i, (R, m) in enumerate(zip(rotations.double().numpy(), mass.double().numpy(), strict=True)):
        lines.append(
            f"mode {i + 1}: mass {m:.3f}  YXY angles (alpha, beta, gamma) = "
            f"({alpha[i]:7.2f}, {beta[i]:7.2f}, {gamma[i]:7.2f}) deg"
        )
        lines += [f"    [{r[0]: .4f} {r[1]: .4f} {r[2]: .4f}]" for r in R]
    return "\n".join(lines)


def predict(
    ckpt_path: str,
    image: str,
    class_index: int | None = None,
    output: str | None = None,
    top_k: int = 5,
    level: int = 5,
    radius_deg: float = 20.0,
    threshold: float | None = None,
    device: str = "cpu",
) -> dict:
    """Print the top-k modes of the distribution for one image and write its plot.

    The plot goes to ``output`` or, by default, next to the image as ``<image stem>_so3.png``; an
    existing file is never overwritten. Returns ``{"rotations", "mass", "plot"}``.
    """
    from image2sphere.plot import plot_so3_distribution, save_figure

    image_path = Path(image)
    if not image_path.is_file():
        raise FileNotFoundError(f"image not found: {image_path}")
    plot_path = Path(output) if output else image_path.with_name(f"{image_path.stem}_so3.png")
    if plot_path.exists():
        raise FileExistsError(f"{plot_path} exists; choose another output=<path.png>")
    predictor = Predictor.from_checkpoint(ckpt_path, device)
    dist = predictor(image_path, class_index)
    rotations, mass = dist.modes(level, k=top_k, radius_deg=radius_deg, threshold=threshold)[0]
    print(f"{image_path}: {len(mass)} modes (level {level}, radius {radius_deg:g} deg), "
          f"{float(mass.sum()):.3f} of the probability in them")  # fmt: skip
    print(format_modes(rotations.cpu(), mass.cpu()))
    fig = plot_so3_distribution(dist, level=level, threshold=threshold, title=image_path.name)
    save_figure(fig, plot_path)
    print(f"plot: {plot_path}")
    return {"rotations": rotations, "mass": mass, "plot": plot_path}
