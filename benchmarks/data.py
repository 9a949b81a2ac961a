"""Benchmark: images per second of every dataset reader against a ResNet-50 training step, measured in one run.

Each reader is its DataModule as ``conf/dataset/<config>.yaml`` configures it (augmentation, label
choice, synthetic mix, ``cache_images``), on a small copy of its dataset written into a temporary
folder, every image at ``--image-size`` (224) px:

* ``symsol`` (``symsol1.yaml``): SYMSOL PNG files (:mod:`image2sphere.data.fixtures.symsol`);
* ``modelnet10`` (``modelnet10.yaml``): ModelNet10-SO(3) JPEG records in an LMDB
  (:mod:`image2sphere.data.fixtures.modelnet10`);
* ``pascal3d`` (``pascal3d.yaml``): PASCAL3D+ JPEG photos (500x375) warped to the box, mixed 1:3 with
  RenderForCNN PNG crops (:mod:`image2sphere.data.fixtures.pascal3d`);
* ``symsol_rendered`` (``symsol_rendered.yaml``, the built-in default): the project's own renders
  (:func:`image2sphere.data.render.render_symsol`), decoded once into memory (``cache_images``).

For every reader and for ``num_workers`` 0 and ``--workers`` N (default ``auto``, see
docs/datasets.md#loading-speed-and-workers), the DataModule's training loader (persistent workers,
per-worker LMDB environments, the seeded shuffle, corrupt-image collation: what training uses) is
iterated and timed from its first batch on (``start``: the time to that first batch, worker start-up
included; ``setup``: the DataModule's ``setup("fit")``, which is where ``cache_images`` decodes). The
fixtures are small, so items repeat (one long shuffled epoch over repeated indices) and every file
is in the page cache: the disk is not measured, only decoding, augmentation and collation.

The model side is one training step of a torchvision ResNet-50 (random weights) at the same image
size and batch: forward, cross-entropy, backward, SGD step, on ``--device`` (CUDA when present, else
the CPU), median of ``--steps`` after warm-up. Its images/s is an upper bound for a whole I2S step
(the head adds time). The ratio ``loader/model`` = loader images/s / model images/s: below 1 the
loader is the bottleneck (add workers, or CPUs), above 1 the device is.

Usage::

    python benchmarks/data.py                                   # every reader, 224 px, batch 32, workers 0 and auto
    python benchmarks/data.py --readers modelnet10,pascal3d --workers 6 --seconds 20
    OMP_NUM_THREADS=1 python benchmarks/data.py --quick         # smoke run (batch 8, 0.5 s per reader; < 1 min)
"""

from __future__ import annotations

import argparse
import gc
import os
import statistics
import tempfile
import time
from pathlib import Path

# Before torch's first allocation, as `import image2sphere` would do (see src/image2sphere/__init__.py);
# image2sphere is imported before torchvision (which model_rate imports), as it needs.
os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

import torch  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from _machine import cpu_model, load_line  # noqa: E402  (benchmarks/_machine.py, beside this script)
from image2sphere.data.datamodule import ModelNet10DataModule, Pascal3DDataModule, SymsolDataModule  # noqa: E402
from image2sphere.data.fixtures.modelnet10 import write_modelnet10  # noqa: E402
from image2sphere.data.fixtures.pascal3d import write_pascal3d, write_renderforcnn  # noqa: E402
from image2sphere.data.fixtures.symsol import write_symsol  # noqa: E402
from image2sphere.data.loading import EpochDataset, EpochIndex  # noqa: E402
from image2sphere.data.modelnet import close_lmdb_environments  # noqa: E402
from image2sphere.data.workers import auto_num_workers, available_cpus, local_processes  # noqa: E402

CONF = Path(__file__).resolve().parents[1] / "conf" / "dataset"
# reader -> its conf/dataset file
READERS = {
    "symsol": "symsol1",
    "modelnet10": "modelnet10",
    "pascal3d": "pascal3d",
    "symsol_rendered": "symsol_rendered",
}
# fixture sizes: images per shape (SYMSOL), instances per class x views (ModelNet10), images per list (PASCAL3D+)
SIZES = {"full": {"symsol": 32, "modelnet_views": 8, "pascal": 4, "renders": 64},
         "quick": {"symsol": 8, "modelnet_views": 2, "pascal": 2, "renders": 16}}  # fmt: skip
QUICK = {"batch_size": 8, "seconds": 0.5, "steps": 2}
REPEATED_LENGTH = 50_000  # indices of the long epoch the loaders are timed on


# ---------------------------------------------------------------------------------------------- helpers
def dataset_config(reader: str) -> dict:
    """The reader's ``conf/dataset`` settings, without ``_target_`` and the keys that point at files."""
    cfg = OmegaConf.to_container(OmegaConf.load(CONF / f"{READERS[reader]}.yaml"), resolve=False)
    for key in ("_target_", "defaults", "root", "synthetic_root", "render_dir", "seed", "num_workers"):
        cfg.pop(key, None)
    return cfg


class Repeated(EpochDataset):
    """``length`` items cycling over ``data`` (the epoch passed through to it), so that a small fixture
    gives one long epoch without the pause of a new epoch every few batches."""

    def __init__(self, data, length: int):
        self.data = data
        self.length = int(length)

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, key):
        epoch, i = self.epoch_and_index(key)
        i %= len(self.data)
        return self.data[EpochIndex(epoch, i)] if isinstance(self.data, EpochDataset) else self.data[i]

    def init_worker(self) -> None:
        init = getattr(self.data, "init_worker", None)
        if callable(init):
            init()


# ------------------------------------------------------------------------------------------- datasets
def write_fixtures(readers: list[str], root: Path, size: int, sizes: dict) -> dict[str, str]:
    """Write the fixture of each reader under ``root``; returns a description of each."""
    notes = {}
    if "symsol" in readers:
        shapes = tuple(dataset_config("symsol")["shapes"])
        write_symsol(root / "symsol", shapes=shapes, per_split={"train": sizes["symsol"], "test": 1}, image_size=size)
        notes["symsol"] = f"{sizes['symsol'] * len(shapes)} PNG ({len(shapes)} shapes)"
    if "modelnet10" in readers:
        views = sizes["modelnet_views"]
        write_modelnet10(root / "ModelNet10-SO3", instances_per_class=2, image_size=size,
                         views={"train_100V": views, "test_20V": 1})  # fmt: skip
        notes["modelnet10"] = f"{10 * 2 * views} JPEG records in an LMDB"
    if "pascal3d" in readers:
        classes = ("aeroplane", "car", "chair")
        write_pascal3d(root / "PASCAL3D+_release1.1", classes=classes, images_per_list=sizes["pascal"], size=(500, 375))
        write_renderforcnn(root / "syn", classes=classes, models=2, views=2, size=size)
        synthetic = f"{len(classes) * 4} RenderForCNN PNG {size}x{size}"
        notes["pascal3d"] = f"JPEG photos 500x375 of {len(classes)} classes + {synthetic}"
    return notes


def make_datamodule(reader: str, root: Path, size: int, batch_size: int, sizes: dict):
    cfg = dataset_config(reader)
    cfg.update(image_size=size, batch_size=batch_size, num_workers=0, seed=0)
    if reader == "symsol":
        return SymsolDataModule(root=str(root / "symsol"), **{**cfg, "val_per_shape": 0})
    if reader == "modelnet10":
        return ModelNet10DataModule(root=root / "ModelNet10-SO3", **cfg)
    if reader == "pascal3d":
        return Pascal3DDataModule(root=str(root / "PASCAL3D+_release1.1"), synthetic_root=str(root / "syn"),
                                  **{**cfg, "classes": ("aeroplane", "car", "chair")})  # fmt: skip
    cfg["render"] = {**cfg["render"], "train": sizes["renders"], "test": 1, "image_size": size, "progress": False}
    return SymsolDataModule(root=None, render_dir=str(root / "symsol_rendered"), **{**cfg, "val_per_shape": 0})


# ------------------------------------------------------------------------------------------ measurements
def loader_rate(dm, workers: int, seconds: float, batches: int | None) -> dict:
    """Images per second of ``dm``'s training loader with ``workers`` workers, from its first batch on."""
    dm.num_workers = workers
    n_batches = (batches + 1) if batches else None
    length = max(len(dm.data_train), (n_batches * dm.batch_size) if n_batches else REPEATED_LENGTH)
    loader = dm._loader(Repeated(dm.data_train, length), train=True)
    t0 = time.perf_counter()
    images, epoch, start, t_first = 0, 0, None, None
    done = False
    while not done:
        loader.sampler.set_epoch(epoch)
        for k, batch in enumerate(loader):
            now = time.perf_counter()
            if t_first is None:
                t_first, start = now, now - t0
                continue
            images += len(batch["image"])
            if (n_batches and k + 1 >= n_batches) or (not n_batches and now - t_first >= seconds):
                done = True
                break
        epoch += 1
    elapsed = time.perf_counter() - t_first
    del loader  # shuts persistent workers down
    gc.collect()
    return {"workers": workers, "start": start, "rate": images / elapsed if elapsed > 0 else float("inf")}


def model_rate(device: torch.device, batch_size: int, size: int, steps: int, amp: bool) -> tuple[float, float]:
    """(seconds per training step, images per second) of a ResNet-50 at ``size`` px on ``device``."""
    from torchvision.models import resnet50

    torch.manual_seed(0)
    net = resnet50(weights=None).to(device).train()
    opt = torch.optim.SGD(net.parameters(), lr=1e-3, momentum=0.9)
    images = torch.randn(batch_size, 3, size, size, device=device)
    targets = torch.randint(0, 1000, (batch_size,), device=device)

    def step() -> None:
        opt.zero_grad(set_to_none=True)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=amp):
            loss = torch.nn.functional.cross_entropy(net(images), targets)
        loss.backward()
        opt.step()
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    for _ in range(2 if device.type == "cuda" else 1):  # warm-up (cuDNN algorithm choice, allocator)
        step()
    times = []
    for _ in range(steps):
        t = time.perf_counter()
        step()
        times.append(time.perf_counter() - t)
    seconds = statistics.median(times)
    return seconds, batch_size / seconds


# -------------------------------------------------------------------------------------------------- main
def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    p.add_argument("--readers", default=",".join(READERS), help=f"comma-separated, among {', '.join(READERS)}")
    p.add_argument("--batch-size", type=int, default=32, help="images per batch (loader and model)")
    p.add_argument("--workers", default="auto", help="loader workers compared with 0 (an integer or auto)")
    p.add_argument("--seconds", type=float, default=10.0, help="timed seconds per reader and worker count")
    p.add_argument("--batches", type=int, default=None, help="timed batches per reader instead of --seconds")
    p.add_argument("--steps", type=int, default=5, help="timed model steps (median) after warm-up")
    p.add_argument("--image-size", type=int, default=224, help="image side in pixels (loader and model)")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto", help="auto: cuda when present")
    p.add_argument("--amp", action="store_true", help="model step under bfloat16 autocast (precision=bf16-mixed)")
    p.add_argument(
        "--quick",
        action="store_true",
        help="smoke run with small fixtures: " + ", ".join(f"{k.replace('_', '-')} {v}" for k, v in QUICK.items()),
    )
    args = p.parse_args(argv)
    if args.quick:
        for key, value in QUICK.items():
            setattr(args, key, value)
    args.readers = [r.strip() for r in args.readers.split(",") if r.strip()]
    unknown = [r for r in args.readers if r not in READERS]
    if unknown or not args.readers:
        p.error(f"unknown reader(s) {unknown}: choose among {', '.join(READERS)}")
    if args.workers.strip().lower() == "auto":
        args.workers = auto_num_workers(processes=local_processes())
    else:
        try:
            args.workers = int(args.workers)
        except ValueError:
            p.error(f"--workers must be an integer >= 0 or auto, got {args.workers!r}")
        if args.workers < 0:
            p.error(f"--workers must be an integer >= 0 or auto, got {args.workers}")
    for key in ("batch_size", "steps", "image_size"):
        if getattr(args, key) < 1:
            p.error(f"--{key.replace('_', '-')} must be >= 1")
    if args.batches is not None and args.batches < 1:
        p.error("--batches must be >= 1")
    if args.seconds <= 0:
        p.error("--seconds must be > 0")
    if args.device == "cuda" and not torch.cuda.is_available():
        p.error("--device cuda: no CUDA device is available")
    return args


def main(argv=None) -> None:
    args = parse_args(argv)
    t_start = time.perf_counter()
    device = torch.device("cuda" if args.device == "cuda" or (args.device == "auto" and torch.cuda.is_available())
                          else "cpu")  # fmt: skip
    device_name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"{cpu_model()}, no GPU"
    sizes = SIZES["quick" if args.quick else "full"]
    counts = sorted({0, args.workers})
    timed = f"{args.batches} batches" if args.batches else f"{args.seconds:g} s"
    threads = os.environ.get("OMP_NUM_THREADS", "unset")
    print(
        f"image2sphere data-loading benchmark: {cpu_model()} ({available_cpus()} CPUs available), torch "
        f"{torch.__version__}, {torch.get_num_threads()} threads, OMP_NUM_THREADS={threads}"
    )
    print(f"model device: {device.type} ({device_name})")
    print(
        f"settings: {args.image_size} px, batch {args.batch_size}, num_workers {' and '.join(map(str, counts))} "
        f"(auto here: {auto_num_workers(processes=local_processes())}), {timed} timed per reader after its first batch"
        f"{' (--quick)' if args.quick else ''}"
    )
    print(load_line("at start"), flush=True)

    results = []
    with tempfile.TemporaryDirectory(prefix="data_bench_") as tmp:
        root = Path(tmp)
        t0 = time.perf_counter()
        notes = write_fixtures(args.readers, root, args.image_size, sizes)
        print(f"fixtures written into {root} in {time.perf_counter() - t0:.1f} s (small: items repeat):", flush=True)
        for reader in args.readers:
            dm = make_datamodule(reader, root, args.image_size, args.batch_size, sizes)
            t0 = time.perf_counter()
            dm.prepare_data()  # symsol_rendered: renders its set (not timed as loading)
            rendered = time.perf_counter() - t0
            t0 = time.perf_counter()
            dm.setup("fit")
            setup = time.perf_counter() - t0
            if reader == "symsol_rendered":
                notes[reader] = (
                    f"{len(dm.data_train)} renders of {', '.join(dm.shapes)} (rendered in {rendered:.1f} s), "
                    "decoded into memory by setup (cache_images)"
                )
            print(f"  {reader}: {notes[reader]}; {len(dm.data_train)} training items", flush=True)
            for workers in counts:
                r = loader_rate(dm, workers, args.seconds, args.batches)
                r.update(reader=reader, setup=setup)
                results.append(r)
                print(f"    num_workers {workers}: {r['rate']:.1f} images/s (first batch after {r['start']:.2f} s)",
                      flush=True)  # fmt: skip
            del dm
            close_lmdb_environments()

    precision = "bfloat16 autocast" if args.amp else "float32"
    print(
        f"\nmodel: ResNet-50 training step (forward, cross-entropy, backward, SGD) at {args.image_size} px, "
        f"batch {args.batch_size}, {precision} on {device.type}",
        flush=True,
    )
    step, model_ips = model_rate(device, args.batch_size, args.image_size, args.steps, args.amp)
    what = "GPU" if device.type == "cuda" else "CPU"
    print(f"  {step * 1e3:.1f} ms per step (median of {args.steps}): {model_ips:.1f} images/s on the {what}\n")

    cols = [("reader", 16, "<"), ("workers", 7, ">"), ("setup [s]", 9, ">"), ("start [s]", 9, ">"),
            ("images/s", 10, ">"), (f"loader/{what}", 11, ">"), ("bound by", 9, "<")]  # fmt: skip
    print("  ".join(f"{title:{align}{w}}" for title, w, align in cols))
    for r in results:
        ratio = r["rate"] / model_ips
        cells = [r["reader"], str(r["workers"]), f"{r['setup']:.2f}", f"{r['start']:.2f}", f"{r['rate']:.1f}",
                 f"{ratio:.2f}", "loading" if ratio < 1 else what]  # fmt: skip
        print("  ".join(f"{c:{align}{w}}" for c, (_, w, align) in zip(cells, cols, strict=True)))
    print(
        f"\nloader/{what} = loader images/s / {what} images/s of the ResNet-50 step: below 1 the loader cannot keep "
        f"the {what} busy (raise num_workers, up to the CPUs available), above 1 the {what} is the bottleneck. "
        "Fixtures are small synthetic images in the published formats (files in the page cache); real images may "
        "decode slower."
    )
    print(f"total benchmark time: {time.perf_counter() - t_start:.0f} s; {load_line('at end')}")


if __name__ == "__main__":
    main()
