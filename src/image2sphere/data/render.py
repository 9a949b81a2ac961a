"""A writer of the published SYMSOL layout, rendered by :mod:`image2sphere.data.raycast`, and its
command ``python -m image2sphere.data.render``.

Conventions
-----------
* Rotation matrices ``(..., 3, 3)``, column vectors, ``x_camera = R @ x_object`` (docs/conventions.md);
  shapes, object frame and units as in :mod:`image2sphere.data.shapes`; camera, shading and images
  as in :mod:`image2sphere.data.raycast`.

SYMSOL layout written by :func:`render_symsol` (docs/datasets.md#symsol-layout, docs/renderer.md)
--------------------------------------------------------------------------------------------------
``root/{split}/images/{shape}_{i:05d}.png`` (RGB, ``i`` 0-based per shape = row of the npz) and
``root/{split}/rotations.npz``: one key per shape, float32 ``(N, M, 3, 3)``, ``[:, 0]`` the rendering
rotation. For marked shapes ``M`` varies between images; the arrays are NaN-padded to the largest ``M``
of the split (readers treat all-NaN matrices as padding). ``root/render_info.json`` records the
parameters.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import shutil
import sys
import time
import zipfile
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch

from image2sphere.checks import ConfigError, OutputExistsError, check_int
from image2sphere.data.raycast import render
from image2sphere.data.shapes import SHAPES, check_shape, check_shape_list
from image2sphere.data.symmetry import equivalent_rotation_sets
from image2sphere.data.workers import available_cpus
from image2sphere.so3.rotations import random_rotations

__all__ = ["FORMAT_VERSION", "RENDERER_VERSION", "main", "render_symsol", "symsol_rotations"]

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
# Bump whenever the geometry, colours, shading or sampling change (data/shapes.py, data/raycast.py): a cached
# set rendered by another version then no longer matches, and render_symsol refuses it (delete it to render it again).
RENDERER_VERSION = 1

# --------------------------------------------------------------------------------------------------
# Dataset writer
# --------------------------------------------------------------------------------------------------

DEFAULT_SPLITS = {"train": 45000, "test": 5000}  # the public release
_INFO_NAME = "render_info.json"


def _stream_seed(seed: int, split: str, shape: str) -> int:
    """A 63-bit seed from ``(seed, split, shape)`` via SHA-256 (stable across runs, unlike ``hash()``)."""
    digest = hashlib.sha256(f"image2sphere.symsol/{seed}/{split}/{shape}".encode()).digest()
    return int.from_bytes(digest[:8], "little") & ((1 << 63) - 1)


def symsol_rotations(n: int, seed: int, split: str, shape: str) -> torch.Tensor:
    """The ``n`` Haar-random rendering rotations ``(n, 3, 3)`` float64 of ``(seed, split, shape)``.

    Drawn with :func:`image2sphere.so3.random_rotations` from a generator seeded by a stable hash of
    the three; each ``(split, shape)`` has its own stream, so adding a shape changes no other.
    """
    check_int("n", n, 0)
    g = torch.Generator().manual_seed(_stream_seed(seed, split, check_shape(shape)))
    return random_rotations(n, generator=g, dtype=torch.float64)


def _npz_add(zf: zipfile.ZipFile, key: str, array: np.ndarray) -> None:
    """Add ``key.npy`` to an open npz (zip) file, with a fixed timestamp so that the bytes are reproducible.

    ``np.savez`` stamps members with the current time; this writes the same format (stored, zip64 forced).
    """
    info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
    info.compress_type = zipfile.ZIP_STORED
    info.external_attr = 0o644 << 16
    with zf.open(info, mode="w", force_zip64=True) as f:
        np.lib.format.write_array(f, np.ascontiguousarray(array), allow_pickle=False)


def _check_splits(splits) -> dict[str, int]:
    if splits is None:
        return dict(DEFAULT_SPLITS)
    if not isinstance(splits, dict) or not splits:
        raise ConfigError(f"splits must be a non-empty dict {{name: number of images per shape}}, got {splits!r}")
    for name, n in splits.items():
        if not isinstance(name, str) or not name or name.startswith(".") or "/" in name or "\\" in name:
            raise ConfigError(f"splits: invalid split name {name!r} (a plain directory name is needed)")
        check_int(f"splits[{name!r}]", n, 1)
    return dict(splits)


def _is_complete(root: Path, params: dict) -> bool:
    """Whether ``root`` holds every file the parameters call for (npz keys and all images)."""
    for split, n in params["splits"].items():
        npz = root / split / "rotations.npz"
        images = root / split / "images"
        if not npz.is_file() or not images.is_dir():
            return False
        try:
            with zipfile.ZipFile(npz) as zf:
                keys = {name[: -len(".npy")] for name in zf.namelist()}
        except (OSError, zipfile.BadZipFile):
            return False
        if keys != set(params["shapes"]):
            return False
        present = set(os.listdir(images))
        if any(f"{shape}_{i:05d}.png" not in present for shape in params["shapes"] for i in range(n)):
            return False
    return True


def render_symsol(
    root: str | os.PathLike,
    splits: dict[str, int] | None = None,
    shapes: Sequence[str] = SHAPES,
    image_size: int = 224,
    seed: int = 0,
    supersample: int = 2,
    batch_size: int = 64,
    progress: bool = True,
    png_thread: bool | None = None,
) -> dict:
    """Render a SYMSOL-style dataset into ``root`` in the published layout (module docstring).

    ``splits`` maps split names to the number of images per shape (default: 45000 train, 5000 test,
    as published). The rotations of ``(split, shape)`` are :func:`symsol_rotations` of ``seed``, and
    the npz holds :func:`~image2sphere.data.symmetry.equivalent_rotation_sets` in float32 (NaN-padded
    for marked shapes). Equal arguments give byte-identical files; ``batch_size`` (images per
    :func:`~image2sphere.data.raycast.render` call) and ``progress`` do not change the output.

    Caching and safety: ``root/render_info.json`` records the parameters. If ``root`` already holds a
    complete set with the same parameters, nothing is rendered (cache hit). If it exists with other
    parameters or other content (anything but an empty directory), ``FileExistsError`` is raised and
    nothing is touched. The set is rendered into ``root.parent / ".{root.name}.partial-<pid>"``,
    which is renamed to ``root`` only when complete and removed if rendering fails.

    ``png_thread``: encode the PNG files in a helper thread while the next batch renders. The default
    (None) uses it only if torch's intra-op threads leave a CPU free: oversubscribed cores make torch's
    thread pool crawl (10x and worse).

    Returns ``{"root", "cached", "counts": {split: {shape: n}}, "images", "rendered", "seconds",
    "images_per_second"}`` (``rendered`` is 0 on a cache hit).
    """
    root = Path(root)
    splits = _check_splits(splits)
    shapes = check_shape_list(shapes)
    check_int("image_size", image_size, 1)
    check_int("supersample", supersample, 1)
    check_int("batch_size", batch_size, 1)
    check_int("seed", seed, 0)
    params = {
        "format": "SYMSOL",
        "format_version": FORMAT_VERSION,
        "renderer_version": RENDERER_VERSION,
        "splits": splits,
        "shapes": shapes,
        "image_size": image_size,
        "supersample": supersample,
        "seed": seed,
    }
    counts = {split: dict.fromkeys(shapes, n) for split, n in splits.items()}
    total = sum(n * len(shapes) for n in splits.values())
    t0 = time.perf_counter()
    if root.exists():
        info_path = root / _INFO_NAME
        if not root.is_dir():
            raise OutputExistsError(f"{root} exists and is not a directory; choose another directory or delete it")
        if info_path.is_file():
            try:
                existing = json.loads(info_path.read_text())
            except (OSError, ValueError):
                existing = None
            if existing == params and _is_complete(root, params):
                log.info("SYMSOL set in %s is complete with the same parameters: not re-rendering", root)
                return _writer_result(root, counts, total, rendered=0, seconds=time.perf_counter() - t0)
            if isinstance(existing, dict) and existing.get("format") == "SYMSOL" and existing != params:
                raise OutputExistsError(
                    f"{root} holds a SYMSOL set rendered with different parameters ({existing}); "
                    "choose another directory or delete it"
                )
            raise OutputExistsError(
                f"{root} holds an incomplete or unreadable SYMSOL set; choose another directory or delete it"
            )
        if any(root.iterdir()):
            raise OutputExistsError(
                f"{root} already exists and is not a SYMSOL set rendered by this tool; "
                "choose another directory or delete it"
            )
    root.parent.mkdir(parents=True, exist_ok=True)
    partial = root.parent / f".{root.name}.partial-{os.getpid()}"
    if partial.exists():  # left over by an earlier, killed process with our pid: ours to remove
        shutil.rmtree(partial)
    from tqdm.auto import tqdm

    try:
        partial.mkdir()
        if png_thread is None:
            png_thread = torch.get_num_threads() < available_cpus()
        pending: list[Future] = []
        # PNG encoding (zlib, GIL released) overlaps with rendering in one helper thread
        with (
            ThreadPoolExecutor(max_workers=1) if png_thread else _InlineExecutor() as pool,
            tqdm(total=total, disable=not progress, desc=f"rendering SYMSOL into {root}", unit="img") as bar,
        ):
            for split, n in splits.items():
                images_dir = partial / split / "images"
                images_dir.mkdir(parents=True)
                npz_path = partial / split / "rotations.npz"
                with zipfile.ZipFile(npz_path, mode="w", allowZip64=True) as npz:
                    for shape in shapes:  # one shape's array in memory at a time (cyl: 1.2 GB for 45k images)
                        bar.set_postfix(split=split, shape=shape)
                        R = symsol_rotations(n, seed, split, shape)
                        sets, _ = equivalent_rotation_sets(shape, R, dtype=torch.float32)
                        _npz_add(npz, shape, sets.numpy())
                        del sets
                        for start in range(0, n, batch_size):
                            images = render(shape, R[start : start + batch_size], image_size, supersample).numpy()
                            paths = [images_dir / f"{shape}_{i:05d}.png" for i in range(start, start + len(images))]
                            pending.append(pool.submit(_save_pngs, paths, images))
                            while len(pending) > 2:  # bound the images held in memory
                                pending.pop(0).result()
                            bar.update(len(images))
            while pending:
                pending.pop(0).result()
        (partial / _INFO_NAME).write_text(json.dumps(params, indent=2, sort_keys=True) + "\n")
        try:
            os.rename(partial, root)  # atomic; replaces ``root`` only if it is an empty directory
        except OSError as err:
            if _holds_set(root, params):
                # another process (a second run started at the same time) rendered the same set and moved
                # it there first: byte for byte what this one rendered, so use it and drop ours
                shutil.rmtree(partial, ignore_errors=True)
                log.info("%s was completed by another process with the same parameters while rendering: using it", root)
                return _writer_result(root, counts, total, rendered=0, seconds=time.perf_counter() - t0)
            raise OutputExistsError(
                f"{root} appeared or changed while rendering; the new set was not moved there. "
                "Choose another directory or delete it"
            ) from err
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return _writer_result(root, counts, total, rendered=total, seconds=time.perf_counter() - t0)


def _holds_set(root: Path, params: dict) -> bool:
    """Whether ``root`` holds a complete set rendered with ``params`` (its ``render_info.json`` equal)."""
    try:
        existing = json.loads((root / _INFO_NAME).read_text())
    except (OSError, ValueError):
        return False
    return existing == params and _is_complete(root, params)


def _writer_result(root: Path, counts: dict, total: int, rendered: int, seconds: float) -> dict:
    """What :func:`render_symsol` returns; ``rendered == 0`` is a cache hit."""
    speed = 0.0 if rendered == 0 else (rendered / seconds if seconds > 0 else float("inf"))
    return {
        "root": str(root),
        "cached": rendered == 0,
        "counts": counts,
        "images": total,
        "rendered": rendered,
        "seconds": seconds,
        "images_per_second": speed,
    }


class _InlineExecutor:
    """The ``submit`` / context-manager subset of an executor, running each call at once."""

    def submit(self, fn, *args) -> Future:
        future: Future = Future()
        future.set_result(fn(*args))
        return future

    def __enter__(self) -> _InlineExecutor:
        return self

    def __exit__(self, *exc) -> None:
        return None


def _save_pngs(paths: list[Path], images: np.ndarray) -> None:
    """Write RGB ``images`` ``(N, H, W, 3)`` uint8 as PNG files (Pillow's defaults: deterministic bytes)."""
    from PIL import Image

    for path, image in zip(paths, images, strict=True):
        Image.fromarray(image).save(path, format="PNG")


# --------------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------------


def _build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m image2sphere.data.render",
        description="Render a SYMSOL-style dataset (published layout: {split}/images/{shape}_{i:05d}.png, "
        "{split}/rotations.npz) into ROOT. Re-running with the same arguments is a no-op.",
    )
    p.add_argument("root", metavar="ROOT", help="output directory (must not exist, be empty, or hold this set)")
    p.add_argument("--train", type=int, default=DEFAULT_SPLITS["train"], help="train images per shape (0: none)")
    p.add_argument("--test", type=int, default=DEFAULT_SPLITS["test"], help="test images per shape (0: none)")
    p.add_argument("--shapes", nargs="+", default=list(SHAPES), metavar="SHAPE", help=f"any of {' '.join(SHAPES)}")
    p.add_argument("--image-size", type=int, default=224, help="image height and width in pixels")
    p.add_argument("--supersample", type=int, default=2, help="anti-aliasing: rays per pixel along each axis")
    p.add_argument("--seed", type=int, default=0, help="random seed (>= 0)")
    p.add_argument("--batch-size", type=int, default=64, help="images per render call (memory, not output)")
    p.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch intra-op threads (default: CPUs - 1, leaving one CPU to encode PNG files)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point; returns the exit status (argument errors exit with status 2).

    Sets torch's intra-op thread count (``--threads``) for the rest of the process.
    """
    parser = _build_parser()
    args = parser.parse_args(argv)
    unknown = [s for s in args.shapes if s not in SHAPES]
    if unknown:
        parser.error(f"unknown shape(s) {' '.join(unknown)}; valid shapes are {' '.join(SHAPES)}")
    if len(set(args.shapes)) != len(args.shapes):
        parser.error(f"--shapes lists a shape twice: {' '.join(args.shapes)}")
    for name in ("train", "test"):
        if getattr(args, name) < 0:
            parser.error(f"--{name} must be >= 0, got {getattr(args, name)}")
    for name in ("image_size", "supersample", "batch_size"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.seed < 0:
        parser.error(f"--seed must be >= 0, got {args.seed}")
    if args.threads is not None and args.threads < 1:
        parser.error(f"--threads must be >= 1, got {args.threads}")
    splits = {name: n for name, n in (("train", args.train), ("test", args.test)) if n > 0}
    if not splits:
        parser.error("--train and --test are both 0: nothing to render")
    torch.set_num_threads(args.threads or max(1, available_cpus() - 1))
    try:
        result = render_symsol(
            args.root,
            splits=splits,
            shapes=args.shapes,
            image_size=args.image_size,
            seed=args.seed,
            supersample=args.supersample,
            batch_size=args.batch_size,
            progress=not args.no_progress,
        )
    except FileExistsError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    if result["cached"]:
        print(f"{args.root}: complete set with the same parameters already there ({result['images']} images)")
    else:
        print(
            f"rendered {result['rendered']} images into {args.root} in {result['seconds']:.1f} s: "
            f"{result['images_per_second']:.1f} images/second"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
