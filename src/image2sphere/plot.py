"""Pictures of distributions over SO(3), as in IPDF and I2S.

Conventions
-----------
* A rotation is drawn through its XYX Euler angles, ``R = Rx(alpha) @ Ry(beta) @ Rx(gamma)``:
  ``alpha`` is the longitude and ``pi/2 - beta`` the latitude of a point on a Mollweide map (that
  point is the direction ``R @ e_x``), and ``gamma`` (the turn about that direction) its colour on
  an HSV wheel, shown as an inset.
* Grid points are drawn when their probability ``p_i`` reaches ``threshold`` (default ten times
  the uniform probability, or the top probability of a flatter distribution); marker area is
  proportional to ``p_i`` (the most probable point gets ``max_marker_area``). Ground-truth
  rotations are rings in the colour of their own ``gamma``.
* Only the points above the threshold are ever materialised
  (:meth:`image2sphere.distributions.base.PoseDistribution.points_above`), so level 5 (2.36M points)
  is cheap. Figures are plain :class:`matplotlib.figure.Figure` objects (no pyplot state).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure

from image2sphere.checks import ConfigError, OutputExistsError
from image2sphere.distributions.base import PoseDistribution
from image2sphere.so3.grid import so3_healpix_index_to_matrix

__all__ = ["FIGURE_FORMATS", "figure_format", "plot_dataset_item", "plot_reliability", "plot_so3_distribution",
           "rotation_to_plot_coords", "save_figure"]  # fmt: skip

# file extensions save_figure writes, and the format each is written in
FIGURE_FORMATS = {
    "png": "png",
    "jpg": "jpg",
    "jpeg": "jpg",
    "pdf": "pdf",
    "svg": "svg",
    "eps": "eps",
    "ps": "ps",
    "tif": "tif",
    "tiff": "tif",
    "webp": "webp",
}


def rotation_to_plot_coords(R: torch.Tensor | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(longitude, latitude, hue)`` of rotations ``(..., 3, 3)``: radians in ``[-pi, pi]``,
    ``[-pi/2, pi/2]`` and a hue in ``[0, 1)``, from XYX Euler angles (see the module docstring)."""
    R = np.asarray(R.detach().cpu() if isinstance(R, torch.Tensor) else R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise ConfigError(f"rotations must have shape (..., 3, 3), got {R.shape}")
    # R e_x = (cos b, sin a sin b, -cos a sin b); R^T e_x = (cos b, sin b sin g, sin b cos g)
    beta = np.arccos(np.clip(R[..., 0, 0], -1.0, 1.0))
    alpha = np.arctan2(R[..., 1, 0], -R[..., 2, 0])
    gamma = np.arctan2(R[..., 0, 1], R[..., 0, 2])
    return alpha, np.pi / 2 - beta, np.mod(gamma, 2 * np.pi) / (2 * np.pi)


def _colour_wheel(fig: Figure, rect: tuple[float, float, float, float]) -> None:
    from matplotlib import colormaps

    ax = fig.add_axes(rect, projection="polar")
    theta = np.linspace(0, 2 * np.pi, 121)
    radius = np.array([0.6, 1.0])
    ax.pcolormesh(theta, radius, np.tile(theta[:-1] / (2 * np.pi), (1, 1)), cmap=colormaps["hsv"], shading="flat")
    ax.set_yticks([])
    ax.set_xticks(np.radians([0, 90, 180, 270]))
    ax.set_xticklabels(["0", "90", "180", "270"], fontsize=6)
    ax.set_title("third angle (deg)", fontsize=7, pad=2)
    ax.spines["polar"].set_visible(False)


def plot_so3_distribution(
    dist: PoseDistribution | None = None,
    level: int = 5,
    threshold: float | None = None,
    gt_rotations: torch.Tensor | np.ndarray | None = None,
    rotations: torch.Tensor | np.ndarray | None = None,
    probs: torch.Tensor | np.ndarray | None = None,
    title: str | None = None,
    max_marker_area: float = 60.0,
    figsize: tuple[float, float] = (8.0, 4.6),
) -> Figure:
    """Draw one distribution: ``dist`` (batch of one) on the grid of ``level``, or given points.

    Args:
        dist: the distribution; its grid points with ``p_i >= threshold`` are drawn.
        level: grid level (5: the paper's plots).
        threshold: probability below which points are not drawn (default: ``dist.default_threshold``).
        gt_rotations: ``(M, 3, 3)`` ground-truth rotations, drawn as rings.
        rotations, probs: instead of ``dist``, points ``(K, 3, 3)`` and their probabilities ``(K,)``.
        title: figure title.

    The scatter of the points is ``fig.axes[0].collections[0]``; the rings, when given, ``[1]``.
    """
    from matplotlib import colormaps

    if dist is not None:
        if dist.batch_size != 1:
            raise ConfigError(f"plot one distribution at a time (batch of 1), got a batch of {dist.batch_size}")
        if not dist.has_density:  # a point estimate: one point, drawn at full size
            rotations, probs, threshold = dist.mode().detach().cpu().double(), np.ones(1), None
        else:
            threshold = float(dist.default_threshold(level)[0]) if threshold is None else threshold
            index, prob = dist.points_above(threshold, level)[0]
            rotations = so3_healpix_index_to_matrix(index.cpu(), level, dtype=torch.float64)
            probs = prob.cpu().double()
    elif rotations is None or probs is None:
        raise ConfigError("pass dist, or rotations and probs")
    probs = np.asarray(probs.detach().cpu() if isinstance(probs, torch.Tensor) else probs, dtype=np.float64)
    if threshold is not None:
        keep = probs >= threshold
        rotations, probs = np.asarray(rotations)[keep], probs[keep]
    order = np.argsort(probs, kind="stable")  # the most probable points drawn last, on top
    rotations, probs = np.asarray(rotations)[order], probs[order]
    lon, lat, hue = rotation_to_plot_coords(rotations)
    cmap = colormaps["hsv"]

    fig = Figure(figsize=figsize)
    ax = fig.add_axes((0.04, 0.08, 0.78, 0.84), projection="mollweide")
    area = max_marker_area * probs / probs.max() if len(probs) else probs
    ax.scatter(lon, lat, s=area, c=cmap(hue), linewidths=0)
    if gt_rotations is not None:
        g_lon, g_lat, g_hue = rotation_to_plot_coords(gt_rotations)
        ax.scatter(g_lon.reshape(-1), g_lat.reshape(-1), s=max_marker_area * 3, facecolors="none",
                   edgecolors=cmap(g_hue.reshape(-1)), linewidths=1.5)  # fmt: skip
    ax.grid(True, alpha=0.4)
    ax.set_xticklabels([])
    ax.tick_params(labelsize=7)
    if title:
        ax.set_title(title, fontsize=9)
    _colour_wheel(fig, (0.83, 0.6, 0.12, 0.26))
    fig.text(0.84, 0.5, f"{len(probs)} points" + (f"\np >= {threshold:.2g}" if threshold else ""), fontsize=7)
    return fig


@torch.no_grad()
def plot_dataset_item(
    model, item: dict, level: int, threshold: float | None = None, title: str = "", class_names=()
) -> Figure:
    """The predicted distribution of one evaluation item of :mod:`image2sphere.data` (``image``,
    ``class_index``, ``rotations`` with ``mask``: drawn as rings) by ``model`` (a
    :class:`~image2sphere.training.PoseEstimationModule`, whose ``net`` turns its output into a
    distribution). The title gets the item's class name appended."""
    device = next(model.parameters()).device
    output = model(item["image"][None].to(device), item["class_index"][None].to(device))
    c = int(item["class_index"])
    name = class_names[c] if c < len(class_names) else c
    gt = item["rotations"][item["mask"]]
    dist = model.calibrated_distribution(output.float())  # recalibrated, where the model has a fitted temperature
    return plot_so3_distribution(dist, level=level, threshold=threshold, gt_rotations=gt, title=f"{title} ({name})")


def plot_reliability(
    metrics: dict[str, float], class_names: list[str] | tuple[str, ...] = (), title: str | None = None
) -> Figure:
    """Reliability diagram of the calibration metrics (docs/evaluation.md#calibration): the coverage
    ``hdr_coverage_<alpha>`` against the nominal HDR mass ``alpha``, one line per class of
    ``class_names`` that has the keys (``hdr_coverage_<alpha>/<class>``) and a thick line for the mean
    over classes, the diagonal of perfect calibration, each line's ECE in the legend. Where the metrics
    have the recalibrated coverage too (``hdr_coverage_<alpha>_calibrated``, docs/evaluation.md#recalibration),
    its mean over classes is drawn as a second thick line.

    Below the diagonal the truths fall outside the regions more often than they should (over-confident);
    above it, less often (under-confident). ``ValueError`` when ``metrics`` has no calibration (a point
    estimate's).
    """
    from image2sphere.metrics import HDR_COVERAGE_KEYS, HDR_LEVELS

    if not all(key in metrics for key in HDR_COVERAGE_KEYS) or "calibration_ece" not in metrics:
        raise ConfigError(
            "metrics have no calibration (hdr_coverage_10 ... hdr_coverage_90, calibration_ece): "
            "a point estimate has no density to be calibrated"
        )
    levels = np.asarray(HDR_LEVELS)
    fig = Figure(figsize=(5.6, 5.0))
    ax = fig.add_axes((0.12, 0.11, 0.84, 0.8))
    ax.plot([0, 1], [0, 1], color="0.6", linestyle="--", linewidth=1, label="calibrated")
    classes = [c for c in class_names if all(f"{key}/{c}" in metrics for key in HDR_COVERAGE_KEYS)]
    for name in classes:
        coverage = [metrics[f"{key}/{name}"] for key in HDR_COVERAGE_KEYS]
        ece = metrics.get(f"calibration_ece/{name}", math.nan)
        ax.plot(levels, coverage, marker="o", markersize=3, linewidth=1, alpha=0.8, label=f"{name} (ECE {ece:.3f})")
    mean = [metrics[key] for key in HDR_COVERAGE_KEYS]
    label = "mean over classes" if classes else "all test images"
    ax.plot(levels, mean, color="black", marker="o", linewidth=2.5,
            label=f"{label} (ECE {metrics['calibration_ece']:.3f})")  # fmt: skip
    recalibrated = [f"{key}_calibrated" for key in HDR_COVERAGE_KEYS]
    if all(key in metrics for key in recalibrated) and "calibration_ece_calibrated" in metrics:
        temperature, ece = metrics.get("temperature", math.nan), metrics["calibration_ece_calibrated"]
        ax.plot(levels, [metrics[key] for key in recalibrated], color="tab:red", marker="s", linewidth=2.5,
                label=f"{label}, recalibrated (T = {temperature:.3g}, ECE {ece:.3f})")  # fmt: skip
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_aspect("equal")
    ax.grid(True, alpha=0.3)
    ax.set_xlabel("nominal mass alpha of the highest-density region")
    ax.set_ylabel("coverage: fraction of ground truths inside")
    ax.text(0.97, 0.03, "below the diagonal: over-confident\nabove: under-confident", fontsize=7,
            ha="right", va="bottom", color="0.35", transform=ax.transAxes)  # fmt: skip
    ax.legend(fontsize=7, loc="upper left", ncol=2 if len(classes) > 8 else 1)
    if title:
        ax.set_title(title, fontsize=9)
    return fig


def figure_format(path: str | Path, key: str = "path") -> str:
    """The format :func:`save_figure` writes ``path`` in, from its extension (case-insensitive);
    ``ValueError`` naming ``key`` for an extension it does not know. Cheap: call it before computing."""
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix not in FIGURE_FORMATS:
        known = ", ".join(f".{e}" for e in FIGURE_FORMATS)
        got = f"extension .{suffix}" if suffix else "no extension"
        raise ConfigError(f"{key}={path} has {got}: a plot is written as one of {known}; choose such a file name")
    return FIGURE_FORMATS[suffix]


def save_figure(fig: Figure, path: str | Path, dpi: int = 120) -> Path:
    """Write ``fig`` in the format its extension names (:func:`figure_format`: ``.png``, ``.jpg``,
    ``.pdf``, ``.svg``, ...). An existing file is never overwritten (:class:`~image2sphere.checks.OutputExistsError`,
    a ``FileExistsError``); a file that fails half-way is removed."""
    path = Path(path)
    fmt = figure_format(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        f = open(path, "xb")  # noqa: SIM115 - closed by the with block below
    except FileExistsError:
        raise OutputExistsError(f"{path} already exists and is not overwritten: choose another file name") from None
    with f:
        try:
            fig.savefig(f, format=fmt, dpi=dpi)
        except BaseException:
            f.close()
            path.unlink(missing_ok=True)  # only the file this call created
            raise
    return path
