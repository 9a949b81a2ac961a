"""Distributions over SO(3) for your own images from a trained checkpoint.

>>> predictor = Predictor.from_checkpoint("logs/train/runs/<run>/checkpoints/last.ckpt")
>>> dist = predictor(["mug.jpg", "mug2.png"])            # SO3Distribution, batch of 2
>>> modes = dist.modes(level=5, k=5)                      # [(rotations (k, 3, 3), mass (k,)), ...]

Preprocessing is the one the model was trained with: RGB, resized to the run's
``dataset.image_size`` (bilinear), ImageNet normalisation. Images are expected to be framed as the
training images were (e.g. for PASCAL3D+: the object's box, warped or cropped to a square). Files and
PIL images of any mode are converted by :func:`image2sphere.data.common.decode_image`'s rules: 16-bit
and float images scaled to 8 bits, transparency composited onto black.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from image2sphere.checks import ConfigError, InputNotFoundError, check_int
from image2sphere.data.common import image_to_uint8, load_image, normalize_images
from image2sphere.distributions.base import PoseDistribution, check_temperature, check_threshold
from image2sphere.nn.base import method_of
from image2sphere.so3.grid_eval import check_streamed_level
from image2sphere.so3.rotations import matrix_to_angles
from image2sphere.training.checkpoint import build_module, checkpoint_file, load_checkpoint

__all__ = ["Predictor", "format_modes", "free_path", "predict"]

log = logging.getLogger(__name__)

ImageLike = str | Path | Image.Image | np.ndarray | torch.Tensor


class Predictor:
    """A trained pose network with its preprocessing; call it on images to get distributions.

    Args:
        net: the pose network (``num_classes``, ``forward(images[, class_index])``,
            ``output_distribution(output)``: :class:`image2sphere.nn.base.PoseNetwork`).
        image_size: the square input size it was trained with.
        class_names: names of the class indices (for models with class-label input).
        device: where the network runs.
        temperature: the recalibration's temperature (docs/evaluation.md#recalibration): every predicted
            distribution is tempered by it; ``None``: as the network predicts them.
    """

    def __init__(self, net: torch.nn.Module, image_size: int, class_names: Sequence[str] | None = None,
                 device: str | torch.device = "cpu", temperature: float | None = None):  # fmt: skip
        self.device = torch.device(device)
        self.net = net.to(self.device).eval()
        self.image_size = int(image_size)
        self.class_names = list(class_names) if class_names else None
        self.lmax = getattr(net, "lmax", None)
        self.output_distribution = method_of(net)[0]
        self.temperature = None if temperature is None else check_temperature(temperature)

    @classmethod
    def from_checkpoint(
        cls, path: str | Path, device: str | torch.device = "cpu", recalibration: bool = True
    ) -> Predictor:
        """Load a checkpoint of ``python -m src.train`` (``weights_only=True``; see
        :mod:`image2sphere.training.checkpoint`). With ``recalibration`` (the default) its distributions
        are tempered by the temperature stored in the checkpoint, if any."""
        ckpt = load_checkpoint(path)
        module = build_module(ckpt, path)
        image_size = ckpt["run_config"].get("dataset", {}).get("image_size") or module.net.image_size
        fitted = module.recalibration if recalibration else None
        temperature = None if fitted is None else fitted.temperature
        return cls(module.net, int(image_size), module.class_names, device, temperature)

    def preprocess(self, images: ImageLike | Sequence[ImageLike]) -> torch.Tensor:
        """Images (paths, PIL images, uint8 arrays ``(H, W, 3)``) -> normalised ``(B, 3, S, S)``."""
        if isinstance(images, (str, Path, Image.Image)) or (
            isinstance(images, (np.ndarray, torch.Tensor)) and images.ndim == 3
        ):
            images = [images]
        batch = []
        for i, image in enumerate(images):
            if isinstance(image, (str, Path)):
                pixels = load_image(image, self.image_size)
            else:
                if isinstance(image, (np.ndarray, torch.Tensor)):
                    array = np.asarray(image)
                    if array.ndim != 3 or array.shape[-1] != 3 or array.dtype != np.uint8:
                        raise ConfigError(
                            f"image arrays must be uint8 of shape (H, W, 3), got {array.dtype} {array.shape}"
                        )
                    image = Image.fromarray(array)
                pixels = image_to_uint8(image, self.image_size, name=f"number {i}")
            batch.append(normalize_images(pixels))
        if not batch:
            raise ConfigError("no images given")
        return torch.stack(batch).to(self.device)

    @property
    def num_classes(self) -> int:
        """Number of object classes the model takes as input (0: trained without class input)."""
        return int(getattr(self.net, "num_classes", 0) or 0)

    def check_class_index(self, class_index, batch_size: int | None = None) -> torch.Tensor | None:
        """``class_index`` as a long tensor ``(batch_size,)`` (``None`` for a model without class
        input), or ``ValueError``: a model trained without class input takes no ``class_index``; a model
        with class input needs one integer in ``[0, num_classes)`` (or one per image)."""
        n = self.num_classes
        if not n:
            if class_index is not None:
                raise ConfigError(
                    f"this model was trained without class input: leave class_index out (null), got {class_index!r}"
                )
            return None
        names = f" ({', '.join(f'{i}={c}' for i, c in enumerate(self.class_names))})" if self.class_names else ""
        if class_index is None:
            raise ConfigError(f"this model takes the object class as input: pass class_index{names}")
        try:
            values = torch.as_tensor(class_index)
        except (TypeError, ValueError, RuntimeError):
            values = None
        if values is None or values.is_floating_point() or values.is_complex() or values.dtype == torch.bool:
            raise ConfigError(f"class_index must be an integer in [0, {n}){names}, got {class_index!r}")
        values = values.reshape(-1)
        if batch_size is not None and len(values) not in (1, batch_size):
            raise ConfigError(f"class_index must be one integer or one per image ({batch_size}), got {len(values)}")
        bad = values[(values < 0) | (values >= n)]
        if len(bad):
            raise ConfigError(
                f"class_index {bad[0].item()} is out of range: this model knows the classes 0..{n - 1}{names}"
            )
        return values.long().expand(batch_size) if batch_size is not None else values.long()

    @torch.no_grad()
    def __call__(self, images: ImageLike | Sequence[ImageLike], class_index=None) -> PoseDistribution:
        """The predicted distribution for each image (batch in the order given).

        ``class_index``: for models trained with class input, the class of the images (one integer,
        or one per image); must be left out (``None``) for models trained without.
        """
        self.check_class_index(class_index)  # before any image is read
        x = self.preprocess(images)
        classes = self.check_class_index(class_index, len(x))
        output = self.net(x) if classes is None else self.net(x, classes.to(self.device))
        dist = self.output_distribution(output)
        return dist if self.temperature is None else dist.tempered(self.temperature)


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
    recalibration: str = "auto",
) -> dict:
    """Print the top-k modes of the distribution for one image and write its plot.

    The plot goes to ``output`` or, by default, next to the image as ``<image stem>_so3.png``, in the
    format its extension names (``.png``, ``.jpg``, ``.pdf``, ``.svg``, ...). An existing file is never
    overwritten and never stops the prediction: the plot then goes to the first free name
    ``<stem>-1<ext>``, ``<stem>-2<ext>``, ... (:func:`free_path`), and the printed ``plot:`` line says so.
    ``threshold``: a probability in ``(0, 1]``, or ``None`` for the default (ten times the uniform
    probability). When no grid point reaches it, a line says so and the plot is drawn empty.
    ``recalibration``: ``auto`` applies the temperature stored in the checkpoint, if any; ``off`` shows the
    distribution as the network predicts it. Arguments are checked before the checkpoint is loaded.
    Returns ``{"rotations", "mass", "plot"}`` (no modes: ``(0, 3, 3)`` and ``(0,)``).
    """
    from image2sphere.plot import figure_format, plot_so3_distribution, save_figure

    image_path = Path(image)
    if not image_path.is_file():
        raise InputNotFoundError(f"image not found: {image_path}")
    asked = Path(output) if output else image_path.with_name(f"{image_path.stem}_so3.png")
    figure_format(asked, "output")
    level = check_streamed_level(level)
    check_int("top_k", top_k, 1)
    if isinstance(radius_deg, bool) or not isinstance(radius_deg, (int, float)) or not 0 < radius_deg < 180:
        raise ConfigError(f"radius_deg must be in (0, 180) degrees, got {radius_deg!r}")
    if threshold is not None:
        threshold = float(check_threshold(threshold))
    if recalibration not in ("auto", "off"):
        raise ConfigError(f"recalibration must be auto or off, got {recalibration!r}")
    checkpoint_file(ckpt_path)  # not a file (e.g. a run's directory): one line, with the checkpoints found
    predictor = Predictor.from_checkpoint(ckpt_path, device, recalibration=recalibration == "auto")
    if predictor.temperature is not None:
        print(f"recalibrated: temperature {predictor.temperature:.4g} from {ckpt_path} (recalibration=off: without)")
    dist = predictor(image_path, class_index)
    rotations, mass = dist.modes(level, k=top_k, radius_deg=radius_deg, threshold=threshold)[0]
    if len(mass):
        modes, them = ("1 mode", "it") if len(mass) == 1 else (f"{len(mass)} modes", "them")
        print(f"{image_path}: {modes} (level {level}, radius {radius_deg:g} deg), "
              f"{float(mass.sum()):.3f} of the probability in {them}")  # fmt: skip
        print(format_modes(rotations.cpu(), mass.cpu()))
    else:
        top = float(dist.max_prob(level)[0])
        print(f"{image_path}: no modes: no grid point reaches threshold={threshold:g} at level {level} (the most "
              f"probable point has p = {top:.3g}); lower the threshold, or leave it null for the default")  # fmt: skip
    fig = plot_so3_distribution(dist, level=level, threshold=threshold, title=image_path.name)
    while True:
        plot_path = free_path(asked)
        try:
            save_figure(fig, plot_path)  # "x" mode: a file that appeared since free_path is not overwritten
            break
        except FileExistsError:
            if not plot_path.exists():  # not a file written meanwhile (e.g. the folder's name is a file)
                raise
    kept = "" if plot_path == asked else f" ({asked} exists and is kept: the plot got the next free name)"
    print(f"plot: {plot_path}{kept}")
    return {"rotations": rotations, "mass": mass, "plot": plot_path}


def free_path(path: str | Path) -> Path:
    """``path`` if no file is there, else the first of ``<stem>-1<suffix>``, ``<stem>-2<suffix>``, ... that
    does not exist (the same folder and extension)."""
    path = Path(path)
    if not path.exists():
        return path
    number = 1
    while (candidate := path.with_name(f"{path.stem}-{number}{path.suffix}")).exists():
        number += 1
    return candidate
