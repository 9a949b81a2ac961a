"""Check a downloaded dataset before training: ``python -m image2sphere.data.verify DATASET ROOT``.

Prints, per split and class, the number of images found against the number expected, lists the
files that do not decode and any other problem (missing files, bad labels, truncated archives or
databases, pickled data asking for more than numpy arrays, which is refused and never run), and exits
with status 1 when anything is wrong (0 when the copy is complete and readable).

Each dataset's checks are here: :func:`verify_symsol`, :func:`verify_modelnet10` and
:func:`verify_pascal3d`, each returning a :class:`VerifyReport`; the files are read with the readers'
own functions, so a download that passes is one the DataModules read.

Examples::

    python -m image2sphere.data.verify symsol data/symsol
    python -m image2sphere.data.verify modelnet10 data/ModelNet10-SO3
    python -m image2sphere.data.verify pascal3d data/PASCAL3D+_release1.1 \\
        --synthetic data/syn_images_cropped_bkg_overlaid
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import lmdb
import numpy as np

from image2sphere.checks import ConfigError
from image2sphere.data.common import CorruptImageError, DatasetNotFoundError, decode_image
from image2sphere.data.modelnet import lmdb_environment
from image2sphere.data.modelnet_labels import (
    DATASET_NAME,
    DOCS,
    GET_FROM,
    MODELNET10_CLASSES,
    MODELNET10_SPLITS,
    MODELNET10_TEST_INSTANCES,
    MODELNET10_TRAIN_INSTANCES,
    QUATERNION_FILE,
    VIEWS_PER_INSTANCE,
    lmdb_dir,
    parse_view_id,
    quaternion_table,
    read_quaternion_dict,
)
from image2sphere.data.pascal3d_annotations import (
    PASCAL3D_CLASSES,
    RENDERFORCNN_SYNSETS,
    check_classes,
    check_pascal3d_layout,
    check_renderforcnn_layout,
    list_renderforcnn,
    list_split_images,
    read_pascal3d_annotation,
    select_objects,
)
from image2sphere.data.safe_io import DatasetFileError, npz_keys
from image2sphere.data.shapes import SHAPES
from image2sphere.data.symsol_labels import SYMSOL_DOCS, SYMSOL_URL, load_symsol_rotations

__all__ = ["DATASETS", "VerifyReport", "main", "verify", "verify_modelnet10", "verify_pascal3d", "verify_symsol"]

# SYMSOL images per shape in the public release
EXPECTED_PER_SHAPE = {"train": 45000, "test": 5000}
MAX_LISTED = 5  # ModelNet10-SO(3) keys listed per problem; the counts say how many there are in all


@dataclass
class VerifyReport:
    """What a dataset's ``verify`` found: counts per (split, class) against the expected ones,
    files that do not decode, and other problems (missing files, bad labels)."""

    dataset: str
    root: Path
    counts: list[tuple[str, str, int, int | None]] = field(default_factory=list)  # split, class, found, expected
    unreadable: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def count(self, split: str, name: str, found: int, expected: int | None = None) -> None:
        self.counts.append((split, name, int(found), None if expected is None else int(expected)))

    @property
    def mismatches(self) -> list[tuple[str, str, int, int | None]]:
        return [c for c in self.counts if c[3] is not None and c[2] != c[3]]

    @property
    def ok(self) -> bool:
        return not (self.unreadable or self.problems or self.mismatches)

    def decode_files(self, paths, desc: str, progress: bool = True) -> None:
        """Decode every image file of ``paths`` completely (progress bar ``desc``); the ones that do
        not decode are added to :attr:`unreadable`."""
        from tqdm import tqdm

        for path in tqdm(paths, desc=desc, disable=not progress):
            try:
                decode_image(path)
            except CorruptImageError:
                self.unreadable.append(str(path))

    def format(self, max_listed: int = 20) -> str:
        lines = [f"{self.dataset} at {self.root}"]
        if self.counts:
            width = max(len(f"{s}/{c}") for s, c, _, _ in self.counts)
            lines.append(f"  {'split/class':<{width}} {'found':>8} {'expected':>9}")
            for split, name, found, expected in self.counts:
                flag = "" if expected is None or found == expected else "  <-- mismatch"
                exp = "-" if expected is None else str(expected)
                lines.append(f"  {f'{split}/{name}':<{width}} {found:>8} {exp:>9}{flag}")
        for title, items in (("unreadable files", self.unreadable), ("problems", self.problems)):
            if items:
                lines.append(f"  {len(items)} {title}:")
                lines += [f"    {item}" for item in items[:max_listed]]
                if len(items) > max_listed:
                    lines.append(f"    ... and {len(items) - max_listed} more")
        lines += [f"  note: {n}" for n in self.notes]
        lines.append("  OK" if self.ok else "  FAILED")
        return "\n".join(lines)


# --------------------------------------------------------------------------------------------------
# SYMSOL


def verify_symsol(
    root: str | Path, shapes: Sequence[str] | None = None, decode: bool = True, progress: bool = True
) -> VerifyReport:
    """Check a SYMSOL download: per split and shape, images in ``rotations.npz`` against the public
    release's counts (45,000 train and 5,000 test), every listed image present (and decodable when
    ``decode``), every equivalent rotation a finite rotation matrix (see
    :func:`~image2sphere.data.symsol_labels.load_symsol_rotations`). Nothing in ``rotations.npz`` is
    unpickled except numpy arrays (a file asking for more is a problem)."""
    root = Path(root)
    report = VerifyReport("SYMSOL", root)
    if not root.is_dir():
        report.problems.append(
            f"{root} does not exist: expected the unzipped symsol_dataset.zip from {SYMSOL_URL} (see {SYMSOL_DOCS})"
        )
        return report
    for split in ("train", "test"):
        path = root / split / "rotations.npz"
        if not path.is_file():
            report.problems.append(f"missing {path}")
            continue
        try:  # lists the keys only; nothing is unpickled
            present = [k for k in npz_keys(path, f"re-download {SYMSOL_URL} and unzip it again") if k in SHAPES]
        except DatasetFileError as e:
            report.problems.append(str(e))
            continue
        for shape in shapes or present:
            try:
                _, counts = load_symsol_rotations(root / split, [shape])[shape]
            except ValueError as e:
                report.problems.append(str(e))
                continue
            report.count(split, shape, len(counts), EXPECTED_PER_SHAPE[split])
            images = [root / split / "images" / f"{shape}_{i:05d}.png" for i in range(len(counts))]
            missing = [p for p in images if not p.is_file()]
            report.problems += [f"missing image {p}" for p in missing]
            if decode:
                present = [p for p in images if p.is_file()]
                report.decode_files(present, f"decoding {split}/{shape}", progress)
    report.notes.append("the paper mentions 50k training renderings per shape; the public release has 45k + 5k test")
    return report


# --------------------------------------------------------------------------------------------------
# ModelNet10-SO(3)


def _listed(keys: Sequence[str], what: str, limit: int = MAX_LISTED) -> str:
    head = ", ".join(repr(k) for k in keys[:limit])
    more = f" ... ({len(keys)} in all)" if len(keys) > limit else ""
    return f"{len(keys)} {what}: {head}{more}"


def verify_modelnet10(
    root: str | Path,
    splits: Sequence[str] = MODELNET10_SPLITS,
    decode: bool = True,
    progress: bool = True,
) -> VerifyReport:
    """Check a ModelNet10-SO(3) download: the keys of every split's pickle against its LMDB, images
    per class against the published counts (train: instances x 100 or 20 views; test: instances),
    uniform views per instance, labels, and (``decode``) that every record decodes.

    Problems are collected in the returned report, never raised (a missing split is a problem).
    """
    from tqdm.auto import tqdm

    root = Path(root).expanduser()
    report = VerifyReport(DATASET_NAME, root)
    unknown = [s for s in splits if s not in MODELNET10_SPLITS]
    if unknown:
        raise ConfigError(f"splits must be among {MODELNET10_SPLITS}, got {unknown}")
    if not root.is_dir():
        report.problems.append(
            f"{root} does not exist: expected the unpacked ModelNet10-SO3 folder from {GET_FROM} (see {DOCS})"
        )
        return report
    for split in splits:
        directory = lmdb_dir(root, split)
        pkl = directory / QUATERNION_FILE
        absent = [str(p) for p in (directory / "data.mdb", pkl) if not p.is_file()]
        if absent:
            report.problems.append(f"split {split} is missing: {', '.join(absent)} not found")
            continue
        try:
            raw = read_quaternion_dict(pkl)
        except ValueError as e:
            report.problems.append(str(e))
            continue
        if not raw:
            report.problems.append(f"{pkl} lists no views (empty dict)")
        keys, _, quaternion_problems = quaternion_table(pkl, raw)
        if quaternion_problems:
            report.problems.append(f"{pkl}: {len(quaternion_problems)} bad quaternions, e.g. {quaternion_problems[0]}")

        # labels: classes and views per instance
        views_of: Counter[str] = Counter()
        class_of_instance: dict[str, str] = {}
        bad_ids, bad_classes = [], []
        for key in keys:
            try:
                cls, instance = parse_view_id(key)
            except ValueError:
                bad_ids.append(key)
                continue
            if cls not in MODELNET10_CLASSES:
                bad_classes.append(key)
                continue
            views_of[instance] += 1
            class_of_instance[instance] = cls
        if bad_ids:
            report.problems.append(f"{pkl}: " + _listed(bad_ids, "view ids not of the form {class}_{k}.v{j}"))
        if bad_classes:
            report.problems.append(f"{pkl}: " + _listed(bad_classes, "view ids of unknown classes"))
        distribution = Counter(views_of.values())
        if len(distribution) > 1:
            shown = ", ".join(f"{n} instances with {v} views" for v, n in sorted(distribution.items()))
            report.problems.append(f"{split}: views per instance are not uniform ({shown})")
        for cls in MODELNET10_CLASSES:
            instances = [i for i, c in class_of_instance.items() if c == cls]
            images = sum(views_of[i] for i in instances)
            if split in VIEWS_PER_INSTANCE:
                report.count(split, cls, images, MODELNET10_TRAIN_INSTANCES[cls] * VIEWS_PER_INSTANCE[split])
            else:
                report.count(split, cls, images, None)
                report.count(f"{split} (instances)", cls, len(instances), MODELNET10_TEST_INSTANCES[cls])
        if split == "test_20V":
            found = ", ".join(f"{v} views per instance for {n} instances" for v, n in sorted(distribution.items()))
            report.notes.append(
                "the I2S paper (appendix) says the test set has 4 views per instance, while the published folder "
                f"is named test_20V; found {found or 'no views'} ({sum(views_of.values())} images)"
            )

        # the LMDB: its keys against the pickle's, and every record decoded
        try:
            env = lmdb_environment(directory)
            entries = int(env.stat()["entries"])
        except DatasetFileError as e:  # not an LMDB, or truncated
            report.problems.append(str(e))
            continue
        except lmdb.Error as e:
            report.problems.append(f"cannot open the LMDB {directory}: {e}")
            continue
        if entries == 0:
            report.problems.append(f"{directory} is an empty LMDB (no records)")
        lmdb_keys: list[str] = []
        sizes: Counter[tuple[int, int]] = Counter()
        with (
            env.begin(buffers=False) as txn,
            tqdm(total=entries, disable=not progress, desc=f"verifying {split}", unit="img") as bar,
        ):
            records = txn.cursor().iternext(keys=True, values=True) if decode else txn.cursor().iternext(values=False)
            for record in records:
                raw_key, value = record if decode else (record, None)
                key = raw_key.decode("utf-8", errors="backslashreplace")
                lmdb_keys.append(key)
                if decode:
                    try:
                        sizes[decode_image(value, name=f"{directory}:{key}").size] += 1
                    except CorruptImageError:
                        report.unreadable.append(f"{directory}:{key}")
                bar.update()
        in_lmdb, in_pkl = set(lmdb_keys), set(keys)
        missing = sorted(in_pkl - in_lmdb)
        extra = sorted(in_lmdb - in_pkl)
        if missing:
            report.problems.append(f"{directory}: " + _listed(missing, f"keys listed in {QUATERNION_FILE} are missing"))
        if extra:
            report.problems.append(
                f"{directory}: " + _listed(extra, f"records have no quaternion in {QUATERNION_FILE}")
            )
        if sizes:
            shown = ", ".join(f"{w}x{h}: {n}" for (w, h), n in sorted(sizes.items()))
            report.notes.append(f"{split}: image sizes {shown}")
    return report


# --------------------------------------------------------------------------------------------------
# PASCAL3D+ and RenderForCNN


def verify_pascal3d(
    root: str | Path,
    synthetic_root: str | Path | None = None,
    objects: str = "first",
    decode: bool = True,
    decode_synthetic: bool = False,
    progress: bool = True,
    classes: Sequence[str] = PASCAL3D_CLASSES,
) -> VerifyReport:
    """Check a PASCAL3D+ download (and optionally RenderForCNN) before training.

    Per split and class: images listed vs found (every ImageNet-listed image must exist), objects
    kept by the protocol; annotations that do not parse; images that do not decode (real images
    when ``decode``, synthetic ones too when ``decode_synthetic``).
    """
    root = Path(root)
    classes = check_classes(classes)
    report = VerifyReport("PASCAL3D+", root)
    check_pascal3d_layout(root)
    to_decode: list[Path] = []
    for split in ("train", "test"):
        for cls in classes:
            try:
                entries = list_split_images(root, cls, split)
            except FileNotFoundError as e:
                report.problems.append(str(e))
                continue
            listed = [e for e in entries if e[2]]
            report.count(f"{split} imagenet images", cls, sum(e[0].is_file() for e in listed), len(listed))
            report.count(f"{split} pascal images", cls, sum(not e[2] for e in entries))
            kept = 0
            for image, annotation, _ in entries:
                if not image.is_file():
                    report.problems.append(f"missing image {image}")
                    continue
                to_decode.append(image)
                try:
                    objs = read_pascal3d_annotation(annotation)
                except (FileNotFoundError, ValueError) as e:
                    report.problems.append(str(e))
                    continue
                kept += len(select_objects(objs, cls, objects, classes)[0])
            report.count(f"{split} objects kept", cls, kept)
    if decode:
        report.decode_files(to_decode, "decoding PASCAL3D+ images", progress)
    if synthetic_root is not None:
        synthetic_root = Path(synthetic_root)
        check_renderforcnn_layout(synthetic_root)
        views, bad = list_renderforcnn(synthetic_root, classes)
        report.problems += [f"not a RenderForCNN image name: {b}" for b in bad]
        per_class = np.bincount([v.class_index for v in views], minlength=len(classes))
        for cls, n in zip(classes, per_class, strict=True):
            report.count("synthetic images", cls, int(n))
            if n == 0:
                report.problems.append(
                    f"no RenderForCNN images for {cls} ({synthetic_root / RENDERFORCNN_SYNSETS[cls]})"
                )
        if decode_synthetic:
            report.decode_files([v.path for v in views], "decoding RenderForCNN images", progress)
    report.notes.append(
        f"objects={objects!r}; 'pascal images' counts VOC-listed images present in Images/{{cls}}_pascal "
        "(VOC lists name every VOC image, so no expected count)"
    )
    return report


# --------------------------------------------------------------------------------------------------
# Command line


DATASETS = ("symsol", "modelnet10", "pascal3d")


def verify(dataset: str, root: str | Path, decode: bool = True, synthetic: str | None = None,
           decode_synthetic: bool = False, progress: bool = True) -> VerifyReport:  # fmt: skip
    """Run the ``verify`` of ``dataset`` on ``root`` and return its report."""
    if dataset == "symsol":
        return verify_symsol(root, decode=decode, progress=progress)
    if dataset == "modelnet10":
        return verify_modelnet10(root, decode=decode, progress=progress)
    if dataset == "pascal3d":
        return verify_pascal3d(root, synthetic, decode=decode, decode_synthetic=decode_synthetic, progress=progress)
    raise ConfigError(f"dataset must be one of {DATASETS}, got {dataset!r}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m image2sphere.data.verify", description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", choices=DATASETS)
    parser.add_argument("root", help="the dataset folder (as dataset.root in the configs)")
    parser.add_argument("--no-decode", action="store_true", help="only check counts and names, decode nothing")
    parser.add_argument("--synthetic", default=None, help="pascal3d: the RenderForCNN folder to check too")
    parser.add_argument("--decode-synthetic", action="store_true", help="pascal3d: decode every synthetic image")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    try:
        report = verify(args.dataset, args.root, not args.no_decode, args.synthetic, args.decode_synthetic,
                        not args.quiet)  # fmt: skip
    except (DatasetNotFoundError, DatasetFileError) as e:  # the reports collect the rest
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(report.format())
    return 0 if report.ok else 1


if __name__ == "__main__":
    sys.exit(main())
