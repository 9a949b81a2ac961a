"""PASCAL3D+ (release 1.1) and RenderForCNN files in their published layouts: the ``.mat`` annotations,
the image lists, RenderForCNN file names, the protocol's choice of objects and the camera conventions
behind the rotation labels. The images are read by :mod:`image2sphere.data.pascal3d`.

Layout (docs/datasets.md#pascal3d-layout)
-----------------------------------------
``root`` (the unpacked ``PASCAL3D+_release1.1``)::

    Images/{cls}_pascal/{id}.jpg           Images/{cls}_imagenet/{id}.JPEG
    Annotations/{cls}_{pascal|imagenet}/{id}.mat      (record.objects[k])
    Image_sets/{cls}_imagenet_{train|val}.txt         (one id per line)
    PASCAL/VOCdevkit/VOC2012/ImageSets/Main/{cls}_{train|val}.txt   ("id label" per line)

``synthetic_root`` (RenderForCNN, e.g. ``syn_images_cropped_bkg_overlaid``)::

    {synset}/{md5}/{synset}_{md5}_a{az:03d}_e{el:03d}_t{tilt:03d}_d{dist:03d}.png

Protocol and conventions
------------------------
* Train = PASCAL VOC train + ImageNet train + ImageNet val; test = PASCAL VOC val. A VOC list
  names every VOC image with a label; those whose image exists in ``Images/{cls}_pascal`` are used.
* Objects are dropped when occluded, truncated or difficult, without a viewpoint (or without a
  distance, or distance 0), or with a degenerate box. ``objects="first"`` considers only the first
  object of each annotation file (what the I2S and Mohlin et al. code read; its class is its own
  ``class`` field); ``objects="all"`` every object of the folder's category.
* Rotation (GL camera frame: ``x`` right, ``y`` up, ``z`` toward the viewer; ``x_camera = R @
  x_object``) from azimuth ``a``, elevation ``e`` and in-plane ``theta`` (degrees in the files):
  ``R = Rz(theta) @ Rx(e - pi/2) @ Rz(-a)`` (:func:`pascal3d_rotation`). This is the camera of the
  PASCAL3D+ annotation tool: an object point ``X`` projects to the pixel
  ``(px, py) + focal * viewport * (x_cv / z_cv, y_cv / z_cv)`` (1-based) with
  ``x_cv = diag(1, -1, -1) @ R @ (X - C)`` and ``C`` the camera centre at ``distance``.
* RenderForCNN files store the tilt with the opposite sign: ``R = pascal3d_rotation(a, e, -tilt)``.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from image2sphere.checks import ConfigError, InputNotFoundError
from image2sphere.data.common import missing_dataset_error
from image2sphere.so3.rotations import rotation_about_axis

__all__ = [
    "OBJECT_MODES",
    "PASCAL3D_CLASSES",
    "RENDERFORCNN_SYNSETS",
    "Pascal3DObject",
    "SyntheticView",
    "check_classes",
    "check_pascal3d_layout",
    "check_renderforcnn_layout",
    "drop_reason",
    "list_pascal3d_objects",
    "list_renderforcnn",
    "list_split_images",
    "parse_renderforcnn_name",
    "pascal3d_rotation",
    "read_pascal3d_annotation",
    "renderforcnn_rotation",
    "select_objects",
]

PASCAL3D_CLASSES = (
    "aeroplane", "bicycle", "boat", "bottle", "bus", "car",
    "chair", "diningtable", "motorbike", "sofa", "train", "tvmonitor",
)  # fmt: skip
# ShapeNet synsets of the 12 categories: RenderForCNN's folder names
RENDERFORCNN_SYNSETS = {
    "aeroplane": "02691156", "bicycle": "02834778", "boat": "02858304", "bottle": "02876657",
    "bus": "02924116", "car": "02958343", "chair": "03001627", "diningtable": "04379243",
    "motorbike": "03790512", "sofa": "04256520", "train": "04468005", "tvmonitor": "03211117",
}  # fmt: skip
OBJECT_MODES = ("first", "all")
PASCAL3D_URL = "ftp://cs.stanford.edu/cs/cvgl/PASCAL3D+_release1.1.zip (see cvgl.stanford.edu/projects/pascal3d.html)"
RENDERFORCNN_URL = (
    "https://shapenet.cs.stanford.edu/media/syn_images_cropped_bkg_overlaid.tar "
    "(github.com/ShapeNet/RenderForCNN; needs a free ImageNet account)"
)
# RenderForCNN names angles as 3-digit integers (its README: a tilt written t016 is -16 = 344 degrees
# in PASCAL3D+'s convention); a minus sign is accepted too
_SYNTHETIC_NAME = re.compile(r"^(\d{8})_([0-9a-f]+)_a(-?\d+)_e(-?\d+)_t(-?\d+)_d(-?\d+)\.png$")
PASCAL3D_DOCS = "docs/datasets.md#pascal3d-layout"
RENDERFORCNN_DOCS = "docs/datasets.md#renderforcnn-synthetic-images"
_VOC_LISTS = Path("PASCAL", "VOCdevkit", "VOC2012", "ImageSets", "Main")


# --------------------------------------------------------------------------------------------------
# Rotations
# --------------------------------------------------------------------------------------------------


def pascal3d_rotation(azimuth, elevation, theta) -> np.ndarray:
    """``Rz(theta) @ Rx(elevation - pi/2) @ Rz(-azimuth)`` ``(..., 3, 3)`` from angles in degrees (GL frame)."""
    a, e, t = np.broadcast_arrays(*(np.radians(np.asarray(v, dtype=np.float64)) for v in (azimuth, elevation, theta)))
    if not (np.isfinite(a).all() and np.isfinite(e).all() and np.isfinite(t).all()):
        raise ConfigError("azimuth, elevation and theta must be finite")

    def rot(axis: str, angle: np.ndarray) -> np.ndarray:  # float64 Rx / Rz of image2sphere.so3
        return rotation_about_axis(axis, torch.from_numpy(np.array(angle, dtype=np.float64))).numpy()

    return rot("z", t) @ rot("x", e - np.pi / 2) @ rot("z", -a)


def renderforcnn_rotation(azimuth, elevation, tilt) -> np.ndarray:
    """The rotation of a RenderForCNN image from its file-name angles (degrees): the tilt is negated."""
    return pascal3d_rotation(azimuth, elevation, -np.asarray(tilt, dtype=np.float64))


# --------------------------------------------------------------------------------------------------
# Annotations and listing
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Pascal3DObject:
    """One annotated object: where it is and its pose. ``box`` is ``(x1, y1, x2, y2)`` and
    ``principal_point`` ``(px, py)``, both as written in the annotation (1-based, MATLAB)."""

    image: Path
    annotation: Path
    object_index: int
    class_index: int
    box: tuple[float, float, float, float]
    azimuth: float
    elevation: float
    theta: float
    focal_px: float  # focal * viewport
    principal_point: tuple[float, float]

    @property
    def rotation(self) -> np.ndarray:
        return pascal3d_rotation(self.azimuth, self.elevation, self.theta)

    def intrinsics(self) -> np.ndarray:
        """``K`` in continuous pixel coordinates (MATLAB coordinate ``p`` is ``p - 0.5``)."""
        px, py = self.principal_point
        f = self.focal_px
        return np.array([[f, 0.0, px - 0.5], [0.0, f, py - 0.5], [0.0, 0.0, 1.0]])


def _scalar(value) -> float | None:
    a = np.asarray(value).reshape(-1)
    if a.size == 0:
        return None
    try:
        return float(a[0])
    except (TypeError, ValueError):
        return None


def _as_list(value) -> list:
    if isinstance(value, np.ndarray):
        return list(value.reshape(-1))
    return [value]


def read_pascal3d_annotation(path: str | Path) -> list[dict]:
    """The objects of one annotation ``.mat`` file as plain dicts.

    Keys: ``class`` (str), ``bbox`` (4 floats or None), ``truncated``, ``occluded``, ``difficult``
    (bools) and ``viewpoint``: None when absent, else a dict of the numeric fields present
    (``azimuth``, ``elevation``, ``theta``, ``distance``, ``px``, ``py``, ``focal``, ``viewport``).
    Raises ``ValueError`` naming the file when it is not a PASCAL3D+ annotation.
    """
    from scipy.io import loadmat

    path = Path(path)
    try:
        mat = loadmat(path, squeeze_me=True, struct_as_record=False)
        objects = _as_list(mat["record"].objects)
    except FileNotFoundError:
        raise InputNotFoundError(f"annotation file not found: {path}") from None
    except Exception as e:  # scipy raises several types for damaged files
        raise ConfigError(
            f"cannot read PASCAL3D+ annotation {path} ({type(e).__name__}: {e}); expected a .mat file holding "
            f"record.objects (see {PASCAL3D_DOCS})"
        ) from e
    out = []
    for obj in objects:
        fields = set(getattr(obj, "_fieldnames", []))
        vp = getattr(obj, "viewpoint", None)
        viewpoint = None
        if vp is not None and hasattr(vp, "_fieldnames"):
            viewpoint = {k: _scalar(getattr(vp, k)) for k in vp._fieldnames}
            viewpoint = {k: v for k, v in viewpoint.items() if v is not None}
        bbox = np.asarray(getattr(obj, "bbox", []), dtype=np.float64).reshape(-1) if "bbox" in fields else None
        out.append(
            {
                "class": str(getattr(obj, "class", "")),
                "bbox": tuple(bbox.tolist()) if bbox is not None and bbox.size == 4 else None,
                "truncated": bool(_scalar(getattr(obj, "truncated", 0)) or 0),
                "occluded": bool(_scalar(getattr(obj, "occluded", 0)) or 0),
                "difficult": bool(_scalar(getattr(obj, "difficult", 0)) or 0),
                "viewpoint": viewpoint,
            }
        )
    return out


_VIEW_KEYS = ("azimuth", "elevation", "theta", "distance", "px", "py", "focal", "viewport")


def drop_reason(obj: dict) -> str | None:
    """Why an annotated object is left out of the protocol, or ``None`` when it is kept."""
    for flag in ("occluded", "truncated", "difficult"):
        if obj[flag]:
            return flag
    vp = obj["viewpoint"]
    if vp is None or any(k not in vp for k in _VIEW_KEYS if k != "distance"):
        return "no viewpoint"
    if not vp.get("distance"):
        return "distance 0"
    if obj["bbox"] is None:
        return "degenerate box"
    x1, y1, x2, y2 = obj["bbox"]
    if not (np.isfinite(obj["bbox"]).all() and x1 < x2 and y1 < y2):
        return "degenerate box"
    return None


def check_classes(classes: Sequence[str] | str, key: str = "dataset.classes") -> tuple[str, ...]:
    """Validated category names (a subset of :data:`PASCAL3D_CLASSES`, no repeats)."""
    classes = (classes,) if isinstance(classes, str) else tuple(classes)
    unknown = [c for c in classes if c not in PASCAL3D_CLASSES]
    if unknown or not classes or len(set(classes)) != len(classes):
        raise ConfigError(f"{key} must be distinct names among {PASCAL3D_CLASSES}, got {list(classes)}")
    return classes


def _split_sources(root: Path, cls: str, split: str) -> list[tuple[str, Path]]:
    """``(source, list file)`` of one class and split: VOC train / ImageNet train+val, or VOC val."""
    voc = root / _VOC_LISTS
    if split == "train":
        return [
            ("pascal", voc / f"{cls}_train.txt"),
            ("imagenet", root / "Image_sets" / f"{cls}_imagenet_train.txt"),
            ("imagenet", root / "Image_sets" / f"{cls}_imagenet_val.txt"),
        ]
    if split == "test":
        return [("pascal", voc / f"{cls}_val.txt")]
    raise ConfigError(f"split must be 'train' or 'test', got {split!r}")


def _read_ids(path: Path) -> list[str]:
    if not path.is_file():
        raise InputNotFoundError(f"PASCAL3D+ image list not found: {path} (see {PASCAL3D_DOCS})")
    ids = []
    for line in path.read_text().splitlines():
        parts = line.split()
        if parts:
            ids.append(parts[0])
    return ids


def list_split_images(root: str | Path, cls: str, split: str) -> list[tuple[Path, Path, bool]]:
    """``(image, annotation, listed_must_exist)`` for one class and split, in list order.

    VOC lists name every VOC image, so only the ones present in ``Images/{cls}_pascal`` are
    returned (``False``); every id of an ImageNet list must exist (``True``).
    """
    root = Path(root)
    out = []
    for source, list_file in _split_sources(root, cls, split):
        folder = f"{cls}_{source}"
        suffix = ".jpg" if source == "pascal" else ".JPEG"
        for i in _read_ids(list_file):
            image = root / "Images" / folder / f"{i}{suffix}"
            if source == "pascal" and not image.is_file():
                continue
            out.append((image, root / "Annotations" / folder / f"{i}.mat", source == "imagenet"))
    return out


def select_objects(
    annotated: list[dict], cls: str, objects: str, classes: Sequence[str]
) -> tuple[list[tuple[int, dict]], list[str]]:
    """The protocol's choice among the objects of one annotation file of folder ``cls``.

    ``objects="first"``: only the first object (with its own class); ``"all"``: the objects of class
    ``cls``. Of those, the ones that pass :func:`drop_reason` and whose class is in ``classes`` are
    returned as ``(object index, object)``, with the reasons the others were dropped.
    """
    candidates = list(enumerate(annotated))
    candidates = candidates[:1] if objects == "first" else [(k, o) for k, o in candidates if o["class"] == cls]
    kept, reasons = [], []
    for k, obj in candidates:
        reason = drop_reason(obj)
        if reason is None and obj["class"] not in classes:
            reason = "class not selected"
        if reason is None:
            kept.append((k, obj))
        else:
            reasons.append(reason)
    return kept, reasons


def list_pascal3d_objects(
    root: str | Path, split: str, objects: str = "first", classes: Sequence[str] = PASCAL3D_CLASSES
) -> tuple[list[Pascal3DObject], dict[str, int]]:
    """The objects of a split that the protocol keeps, and how many were dropped for each reason.

    ``class_index`` is the position in ``classes``. Raises ``FileNotFoundError`` naming the first
    missing image or annotation file.
    """
    if objects not in OBJECT_MODES:
        raise ConfigError(f"dataset.objects must be one of {OBJECT_MODES}, got {objects!r}")
    classes = check_classes(classes)
    kept: list[Pascal3DObject] = []
    dropped: dict[str, int] = {}
    for cls in classes:
        for image, annotation, _ in list_split_images(root, cls, split):
            if not image.is_file():
                raise InputNotFoundError(f"image listed for PASCAL3D+ {split} is missing: {image}")
            chosen, reasons = select_objects(read_pascal3d_annotation(annotation), cls, objects, classes)
            for reason in reasons:
                dropped[reason] = dropped.get(reason, 0) + 1
            for k, obj in chosen:
                vp = obj["viewpoint"]
                kept.append(
                    Pascal3DObject(
                        image=image,
                        annotation=annotation,
                        object_index=k,
                        class_index=classes.index(obj["class"]),
                        box=obj["bbox"],
                        azimuth=vp["azimuth"],
                        elevation=vp["elevation"],
                        theta=vp["theta"],
                        focal_px=vp["focal"] * vp["viewport"],
                        principal_point=(vp["px"], vp["py"]),
                    )
                )
    return kept, dropped


@dataclass(frozen=True)
class SyntheticView:
    """One RenderForCNN image and the angles in its file name (degrees; ``tilt`` as stored)."""

    path: Path
    class_index: int
    azimuth: float
    elevation: float
    tilt: float

    @property
    def rotation(self) -> np.ndarray:
        return renderforcnn_rotation(self.azimuth, self.elevation, self.tilt)


def parse_renderforcnn_name(name: str) -> tuple[str, int, int, int, int]:
    """``(synset, azimuth, elevation, tilt, distance)`` from a RenderForCNN file name."""
    m = _SYNTHETIC_NAME.match(name)
    if m is None:
        raise ConfigError(
            f"{name!r} is not a RenderForCNN image name ({{synset}}_{{md5}}_a{{az}}_e{{el}}_t{{tilt}}_d{{dist}}.png; "
            f"see {RENDERFORCNN_DOCS})"
        )
    synset, _, a, e, t, d = m.groups()
    return synset, int(a), int(e), int(t), int(d)


def list_renderforcnn(
    root: str | Path, classes: Sequence[str] = PASCAL3D_CLASSES
) -> tuple[list[SyntheticView], list[str]]:
    """All RenderForCNN images of ``classes`` (sorted; ``class_index`` is the position in
    ``classes``), and the file names that do not parse."""
    root = Path(root)
    classes = check_classes(classes)
    views, bad = [], []
    for cls in classes:
        synset = RENDERFORCNN_SYNSETS[cls]
        folder = root / synset
        if not folder.is_dir():
            continue
        for model in sorted(os.scandir(folder), key=lambda e: e.name):
            if not model.is_dir():
                continue
            for entry in sorted(os.scandir(model.path), key=lambda e: e.name):
                if not entry.name.endswith(".png"):
                    continue
                try:
                    s, a, e, t, _ = parse_renderforcnn_name(entry.name)
                except ValueError:
                    bad.append(entry.path)
                    continue
                if s != synset:
                    bad.append(entry.path)
                    continue
                views.append(SyntheticView(Path(entry.path), classes.index(cls), a, e, t))
    return views, bad


# --------------------------------------------------------------------------------------------------
# Layout checks
# --------------------------------------------------------------------------------------------------


def check_pascal3d_layout(root: Path) -> None:
    needed = [root / "Images", root / "Annotations", root / "Image_sets", root / _VOC_LISTS]
    if not root.is_dir() or not all(p.is_dir() for p in needed):
        missing = [str(p.relative_to(root)) for p in needed if not p.is_dir()] if root.is_dir() else []
        raise missing_dataset_error(
            "PASCAL3D+",
            root,
            "the unpacked PASCAL3D+_release1.1 folder with Images/, Annotations/, Image_sets/ and "
            f"{_VOC_LISTS.as_posix()}/" + (f" (missing: {', '.join(missing)})" if missing else ""),
            PASCAL3D_URL,
            "dataset.root",
            PASCAL3D_DOCS,
        )


def check_renderforcnn_layout(root: Path) -> None:
    if not root.is_dir() or not any((root / s).is_dir() for s in RENDERFORCNN_SYNSETS.values()):
        raise missing_dataset_error(
            "RenderForCNN synthetic images",
            root,
            "one folder per ShapeNet synset (e.g. 02691156/ for aeroplane) holding "
            "{md5}/{synset}_{md5}_a{az}_e{el}_t{tilt}_d{dist}.png",
            RENDERFORCNN_URL + "; or train without them: dataset.synthetic_root=null",
            "dataset.synthetic_root",
            RENDERFORCNN_DOCS,
        )
