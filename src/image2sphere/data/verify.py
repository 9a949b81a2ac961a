"""Check a downloaded dataset before training: ``python -m image2sphere.data.verify DATASET ROOT``.

Prints, per split and class, the number of images found against the number expected, lists the
files that do not decode and any other problem (missing files, bad labels, truncated archives or
databases, pickled data asking for more than numpy arrays, which is refused and never run), and exits
with status 1 when anything is wrong (0 when the copy is complete and readable).

Examples::

    python -m image2sphere.data.verify symsol data/symsol
    python -m image2sphere.data.verify modelnet10 data/ModelNet10-SO3
    python -m image2sphere.data.verify pascal3d data/PASCAL3D+_release1.1 \\
        --synthetic data/syn_images_cropped_bkg_overlaid
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from image2sphere.data.common import DatasetNotFoundError, VerifyReport
from image2sphere.data.safe_io import DatasetFileError

DATASETS = ("symsol", "modelnet10", "pascal3d")


def verify(dataset: str, root: str | Path, decode: bool = True, synthetic: str | None = None,
           decode_synthetic: bool = False, progress: bool = True) -> VerifyReport:  # fmt: skip
    """Run the ``verify`` of ``dataset`` on ``root`` and return its report."""
    if dataset == "symsol":
        from image2sphere.data.symsol import verify_symsol

        return verify_symsol(root, decode=decode, progress=progress)
    if dataset == "modelnet10":
        from image2sphere.data.modelnet import verify_modelnet10

        return verify_modelnet10(root, decode=decode, progress=progress)
    if dataset == "pascal3d":
        from image2sphere.data.pascal3d import verify_pascal3d

        return verify_pascal3d(root, synthetic, decode=decode, decode_synthetic=decode_synthetic, progress=progress)
    raise ValueError(f"dataset must be one of {DATASETS}, got {dataset!r}")


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
