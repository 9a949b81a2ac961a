"""Every DataModule with DataLoader workers: the same items in the same order as without workers
(forkserver, the default, fork and spawn), the epoch reaching persistent workers, resume within an epoch,
LMDB environments per worker, every dataset through pickle, the workers' signals under a fork server, and
the ``num_workers`` / ``multiprocessing_context`` / ``pin_memory`` settings.

The datasets are the published-layout fixtures of :mod:`image2sphere.data.fixtures`.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import time
from pathlib import Path

import lightning.pytorch as pl
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from image2sphere.data import common, modelnet
from image2sphere.data.datamodule import ModelNet10DataModule, Pascal3DDataModule, SymsolDataModule
from image2sphere.data.fixtures.modelnet10 import write_modelnet10
from image2sphere.data.fixtures.pascal3d import write_pascal3d, write_renderforcnn
from image2sphere.data.fixtures.symsol import write_symsol
from image2sphere.data.loading import EpochIndex, EpochShuffleSampler
from image2sphere.data.modelnet import ModelNet10Dataset, close_lmdb_environments
from image2sphere.data.pascal3d import SyntheticViews
from image2sphere.data.pascal3d_annotations import SyntheticView
from image2sphere.data.workers import (
    DEFAULT_START_METHOD,
    FORKSERVER_PRELOAD,
    auto_num_workers,
    check_multiprocessing_context,
    check_num_workers,
    init_worker,
    local_processes,
)
from image2sphere.testing.commands import group_alive, process_group

REPO = Path(__file__).resolve().parents[1]
DATASETS = ("modelnet10", "pascal3d", "symsol")
PASCAL_CLASSES = ("aeroplane", "car")


@pytest.fixture(autouse=True)
def _close_environments():
    yield
    close_lmdb_environments()


@pytest.fixture(scope="module")
def roots(tmp_path_factory) -> dict[str, Path]:
    """Small copies of the three published layouts (written once for the module)."""
    base = tmp_path_factory.mktemp("published")
    write_modelnet10(base / "ModelNet10-SO3", instances_per_class=1, views={"train_100V": 3, "test_20V": 2})
    write_pascal3d(base / "PASCAL3D+_release1.1", classes=PASCAL_CLASSES, images_per_list=3)
    write_renderforcnn(base / "syn", classes=PASCAL_CLASSES, models=2, views=2)
    write_symsol(base / "symsol", shapes=("cube", "tetX"), per_split={"train": 8, "test": 3}, image_size=24)
    return {"base": base}


def make_datamodule(name: str, roots: dict[str, Path], num_workers=0, **kwargs):
    base = roots["base"]
    common_args = {"batch_size": 4, "num_workers": num_workers, "seed": 3, **kwargs}
    if name == "modelnet10":
        dm = ModelNet10DataModule(base / "ModelNet10-SO3", image_size=24, **common_args)
    elif name == "pascal3d":
        dm = Pascal3DDataModule(
            root=str(base / "PASCAL3D+_release1.1"), synthetic_root=str(base / "syn"), image_size=24,
            classes=PASCAL_CLASSES, **common_args,
        )  # fmt: skip
    else:
        dm = SymsolDataModule(root=str(base / "symsol"), shapes=["cube", "tetX"], image_size=16, **common_args)
    dm.setup("fit")
    dm.setup("test")
    return dm


def epoch_batches(loader, epoch: int | None = None) -> list[dict]:
    """The batches of one pass over ``loader``, after ``set_epoch(epoch)`` as Lightning calls it."""
    if epoch is not None:
        loader.sampler.set_epoch(epoch)
    return list(loader)


def assert_same_batches(got: list[dict], expected: list[dict]) -> None:
    assert len(got) == len(expected) > 0
    for k, (a, b) in enumerate(zip(got, expected, strict=True)):
        assert set(a) == set(b), k
        for key in b:
            torch.testing.assert_close(
                a[key], b[key], rtol=0, atol=0, msg=lambda m, k=k, key=key: f"batch {k} {key}: {m}"
            )


def labels(batches: list[dict]) -> torch.Tensor:
    return torch.cat([b["rotation"] for b in batches])


# ------------------------------------------------------------------------------------------ same items


def parent_of(pid: int) -> int:
    stat = Path(f"/proc/{pid}/stat").read_text()
    return int(stat[stat.rindex(")") + 2 :].split()[1])


@pytest.mark.parametrize("name", DATASETS)
def test_two_workers_give_the_items_of_zero_workers(roots, name):
    """By default the workers start from a fork server (not forked from this process, whose threads could
    hold an interpreter lock at fork), and give the batches of 0 workers."""
    reference = make_datamodule(name, roots, num_workers=0)
    dm = make_datamodule(name, roots, num_workers=2)
    assert dm.multiprocessing_context == DEFAULT_START_METHOD == "forkserver"
    for make in ("train_dataloader", "test_dataloader"):
        zero, two = getattr(reference, make)(), getattr(dm, make)()
        assert zero.num_workers == 0 and not zero.persistent_workers and zero.multiprocessing_context is None
        assert two.num_workers == 2 and two.persistent_workers and two.worker_init_fn is init_worker
        assert two.multiprocessing_context.get_start_method() == "forkserver"
        epoch = 0 if make == "train_dataloader" else None
        expected = epoch_batches(zero, epoch)
        assert_same_batches(epoch_batches(two, epoch), expected)
        assert all(parent_of(w.pid) != os.getpid() for w in two._iterator._workers)  # the fork server's children
        seen = sum(len(b["index"]) for b in expected)
        assert seen == len(zero.dataset)  # every item, no dropped last batch
    assert {"image", "class_index", "index", "rotation"} <= set(epoch_batches(reference.train_dataloader(), 0)[0])


@pytest.mark.parametrize("name", DATASETS)
def test_persistent_workers_follow_the_epoch(roots, name):
    """Epoch 1 after epoch 0 with 2 persistent workers = epoch 1 with 0 workers (labels, augmentation,
    synthetic draws and the shuffle all follow (seed, epoch, index))."""
    dm = make_datamodule(name, roots, num_workers=2)
    loader = dm.train_dataloader()
    first = epoch_batches(loader, 0)
    workers = loader._iterator
    second = epoch_batches(loader, 1)
    assert loader._iterator is workers  # the same worker processes served both epochs

    reference = make_datamodule(name, roots, num_workers=0)
    assert_same_batches(second, epoch_batches(reference.train_dataloader(), 1))
    assert_same_batches(first, epoch_batches(reference.train_dataloader(), 0))
    order = [torch.cat([b["index"] for b in batches]) for batches in (first, second)]
    assert not torch.equal(order[0], order[1])  # a new shuffle
    if name != "modelnet10":  # the per-epoch randomness of the items themselves: same index, new item
        by_index = [dict(zip(o.tolist(), labels(b), strict=True)) for o, b in zip(order, (first, second), strict=True)]
        assert any(not torch.equal(by_index[0][i], by_index[1][i]) for i in by_index[0])


class _Recorder(pl.LightningModule):
    """Records the epoch, indices and labels of every training batch Lightning gives it."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.zeros(()))
        self.seen: list[tuple[int, torch.Tensor, torch.Tensor]] = []

    def training_step(self, batch, batch_idx):
        self.seen.append((self.current_epoch, batch["index"].clone(), batch["rotation"].clone()))
        return self.w * batch["image"].mean()

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


@pytest.mark.filterwarnings("ignore:You passed in a `val_dataloader`", "ignore:`isinstance\\(treespec, LeafSpec\\)`")
def test_lightning_training_with_persistent_workers_sees_the_batches_of_zero_workers(roots):
    """Through a real Trainer.fit of 3 epochs: Lightning's set_epoch reaches the persistent workers."""
    seen = {}
    for workers in (0, 2):
        module = _Recorder()
        trainer = pl.Trainer(
            max_epochs=3, logger=False, enable_checkpointing=False, enable_progress_bar=False,
            enable_model_summary=False, limit_val_batches=0, accelerator="cpu", devices=1,
        )  # fmt: skip
        trainer.fit(module, make_datamodule("symsol", roots, num_workers=workers))
        seen[workers] = module.seen
    assert [s[0] for s in seen[2]] == [s[0] for s in seen[0]] and {s[0] for s in seen[0]} == {0, 1, 2}
    for (epoch, index0, label0), (_, index2, label2) in zip(seen[0], seen[2], strict=True):
        assert torch.equal(index0, index2) and torch.equal(label0, label2), f"epoch {epoch}"


@pytest.mark.parametrize("name", ["pascal3d", "symsol"])
def test_resume_within_an_epoch_with_workers(roots, name):
    """A run resumed after the first batch of epoch 1 gets the rest of that epoch's batches."""
    reference = make_datamodule(name, roots, num_workers=0)
    whole = epoch_batches(reference.train_dataloader(), 1)
    dm = make_datamodule(name, roots, num_workers=2)
    dm.resume_within_epoch(1, 1)
    loader = dm.train_dataloader()
    assert_same_batches(epoch_batches(loader, 1), whole[1:])
    assert_same_batches(epoch_batches(loader, 2), epoch_batches(reference.train_dataloader(), 2))  # later: whole


def test_sampler_passes_the_epoch_only_to_epoch_datasets(roots):
    dm = make_datamodule("symsol", roots)
    sampler = dm.train_dataloader().sampler
    sampler.set_epoch(4)
    pairs = list(sampler)
    assert all(isinstance(p, EpochIndex) and p.epoch == 4 for p in pairs)
    plain = EpochShuffleSampler(len(pairs), seed=3)
    plain.set_epoch(4)
    assert [p.index for p in pairs] == list(plain)
    # an EpochIndex names its epoch; a plain index takes the last set_epoch
    data = dm.data_train
    data.set_epoch(0)
    paired = data[EpochIndex(4, 5)]
    assert data.epoch == 0 and int(paired["index"]) == int(data[5]["index"])
    data.set_epoch(4)
    torch.testing.assert_close(paired["rotation"], data[5]["rotation"], rtol=0, atol=0)
    assert isinstance(list(make_datamodule("modelnet10", roots).train_dataloader().sampler)[0], int)


# ------------------------------------------------------------------------------------- LMDB per process


class _ProbeDataset(ModelNet10Dataset):
    """Items that also say which process made them and how many LMDB environments it holds that
    another process opened."""

    def __getitem__(self, i):
        item = super().__getitem__(i)
        pid = os.getpid()
        item["pid"] = torch.tensor(pid)
        item["foreign"] = torch.tensor(sum(owner != pid for owner, _ in modelnet._ENVIRONMENTS.values()))
        return item


def test_forked_workers_close_inherited_environments_and_open_their_own(roots):
    dm = make_datamodule("modelnet10", roots, num_workers=2, multiprocessing_context="fork")
    assert len(modelnet._ENVIRONMENTS) == 2  # the constructor opened both splits' LMDBs here
    data = dm.data_train
    dm.data_train = _ProbeDataset(data.root, data.split, data.rows, image_size=data.image_size, labels=data.labels)
    parent_envs = dict(modelnet._ENVIRONMENTS)
    batches = epoch_batches(dm.train_dataloader(), 0)
    pids = set(torch.cat([b["pid"] for b in batches]).tolist())
    assert os.getpid() not in pids and len(pids) >= 1
    assert all(int(b["foreign"].max()) == 0 for b in batches)  # the test split's inherited env was closed too
    assert modelnet._ENVIRONMENTS == parent_envs  # the parent's environments are untouched
    with parent_envs[str(data.lmdb_dir.resolve())][1].begin() as txn:
        assert txn.get(data.labels.keys[0].encode()) is not None


@pytest.mark.slow
def test_spawned_workers_read_modelnet_without_pickling_the_environment(roots):
    reference = make_datamodule("modelnet10", roots, num_workers=0)
    dm = make_datamodule("modelnet10", roots, num_workers=2)
    dm.multiprocessing_context = "spawn"
    dm.data_test[0]  # the environment is open in this process when the workers start
    assert dm.data_test._env is not None and pickle.loads(pickle.dumps(dm.data_test))._env is None
    loader = dm.train_dataloader()
    assert loader.multiprocessing_context.get_start_method() == "spawn"
    assert_same_batches(epoch_batches(loader, 0), epoch_batches(reference.train_dataloader(), 0))
    assert_same_batches(epoch_batches(loader, 1), epoch_batches(reference.train_dataloader(), 1))
    assert_same_batches(list(dm.test_dataloader()), list(reference.test_dataloader()))


@pytest.mark.slow
def test_what_a_fork_server_preloads_does_not_import_lightning():
    """A loader worker unpickles its Dataset, and the fork server preloads what that needs
    (FORKSERVER_PRELOAD) and the main module: none of it imports Lightning, torchmetrics or torchvision (the
    LightningDataModules live in image2sphere.data.datamodule; the entry points import the pipeline in main)."""
    code = (
        "import sys, importlib\n"
        f"for name in {[*FORKSERVER_PRELOAD, 'src.train', 'src.eval', 'src.predict']!r}:\n"
        "    importlib.import_module(name)\n"
        "import image2sphere.data.symsol, image2sphere.data.modelnet, image2sphere.data.pascal3d\n"
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'lightning', 'torchmetrics', 'torchvision'}))"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip() == "[]", proc.stdout


@pytest.mark.slow
def test_spawned_workers_follow_the_epoch_for_symsol(roots):
    dm = make_datamodule("symsol", roots, num_workers=2)
    dm.multiprocessing_context = "spawn"
    loader = dm.train_dataloader()
    epoch_batches(loader, 0)
    reference = make_datamodule("symsol", roots, num_workers=0)
    assert_same_batches(epoch_batches(loader, 1), epoch_batches(reference.train_dataloader(), 1))


# ------------------------------------------------------------------------------------------- settings


def test_auto_rule():
    assert auto_num_workers(cpus=64, processes=1) == 8  # capped
    assert auto_num_workers(cpus=6, processes=1) == 5  # one CPU left to the training process
    assert auto_num_workers(cpus=2, processes=1) == 1
    assert auto_num_workers(cpus=1, processes=1) == 0
    assert auto_num_workers(cpus=16, processes=4) == 3  # each local process starts its own workers
    assert auto_num_workers(cpus=16, processes=16) == 0
    assert auto_num_workers(cpus=4, processes=8) == 0


@pytest.mark.parametrize("name", DATASETS)
def test_num_workers_auto_resolves_from_cpus_and_local_processes(roots, name, monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(5)), raising=False)
    monkeypatch.delenv("LOCAL_WORLD_SIZE", raising=False)
    for value in ("auto", None, "AUTO"):
        dm = make_datamodule(name, roots, num_workers=value)
        assert dm.num_workers_setting == "auto" and dm.num_workers == 4
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "2")
    assert dm.num_workers == 1 and local_processes() == 2
    monkeypatch.delenv("LOCAL_WORLD_SIZE")
    dm.trainer = type("FakeTrainer", (), {"num_devices": 5})()  # DDP on 5 devices of this machine
    assert dm.num_workers == 0 and dm.train_dataloader().num_workers == 0
    explicit = make_datamodule(name, roots, num_workers=3)
    assert explicit.num_workers == 3 and explicit.num_workers_setting == 3


@pytest.mark.parametrize("name", DATASETS)
@pytest.mark.parametrize("bad", [-1, 1.5, "four", "", True, [2]])
def test_bad_num_workers_name_the_key(roots, name, bad):
    with pytest.raises(ValueError, match=r"dataset\.num_workers must be an integer >= 0 or auto"):
        make_datamodule(name, roots, num_workers=bad)


def test_check_num_workers():
    assert check_num_workers(0) == 0 and check_num_workers(7) == 7
    assert check_num_workers("auto") == check_num_workers(None) == check_num_workers(" Auto ") == "auto"
    with pytest.raises(ValueError, match=r"my\.key must be"):
        check_num_workers(-2, "my.key")


@pytest.mark.parametrize(
    ("config", "expected"),
    [("modelnet10", "auto"), ("pascal3d", "auto"), ("symsol1", "auto"), ("symsol_rendered", 0)],
)
def test_dataset_configs_num_workers(config, expected):
    cfg = OmegaConf.load(REPO / "conf" / "dataset" / f"{config}.yaml")
    assert cfg.num_workers == expected and check_num_workers(cfg.num_workers) == expected
    assert isinstance(cfg.pin_memory, bool)


@pytest.mark.parametrize("cuda", [False, True])
def test_pin_memory_only_with_cuda(roots, cuda, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: cuda)
    dm = make_datamodule("modelnet10", roots, pin_memory=True)
    assert dm.train_dataloader().pin_memory is cuda and dm.test_dataloader().pin_memory is cuda
    assert dm.pin_memory is True  # the setting is kept
    off = make_datamodule("modelnet10", roots, pin_memory=False)
    assert off.train_dataloader().pin_memory is False


def test_datasets_decode_in_getitem_not_up_front(roots, monkeypatch):
    """Without cache_images, setting up a DataModule decodes no image: the workers do."""
    calls = []
    real = common.decode_image

    def counting(*args, **kwargs):
        calls.append(args[0])
        return real(*args, **kwargs)

    for module in (common, modelnet):
        monkeypatch.setattr(module, "decode_image", counting, raising=False)
    from image2sphere.data import pascal3d

    monkeypatch.setattr(pascal3d, "decode_image", counting)
    for name in DATASETS:
        make_datamodule(name, roots)
    assert calls == []
    make_datamodule("pascal3d", roots).data_train[np.int64(0)]
    assert len(calls) == 1


# ------------------------------------------------------------------------------------ the start method


@pytest.mark.parametrize("name", DATASETS)
@pytest.mark.parametrize("bad", ["thread", "", "fork server", 1, True, ["fork"]])
def test_bad_multiprocessing_context_names_the_key(roots, name, bad):
    with pytest.raises(
        ValueError, match=r"dataset\.multiprocessing_context must be one of fork, forkserver, spawn or null"
    ):
        make_datamodule(name, roots, multiprocessing_context=bad)


def test_check_multiprocessing_context():
    assert check_multiprocessing_context(None) is None  # the default, resolved where the loaders are made
    assert [check_multiprocessing_context(m) for m in ("fork", " Spawn", "FORKSERVER")] == [
        "fork",
        "spawn",
        "forkserver",
    ]
    with pytest.raises(ValueError, match=r"^my\.key must be one of fork, forkserver, spawn or null .*got 'threads'"):
        check_multiprocessing_context("threads", "my.key")


@pytest.mark.parametrize("method", ["fork", "spawn", "forkserver", None])
def test_the_start_method_set_is_the_loaders(roots, method):
    dm = make_datamodule("symsol", roots, num_workers=1, multiprocessing_context=method)
    assert dm.multiprocessing_context == (method or "forkserver")
    assert dm.train_dataloader().multiprocessing_context.get_start_method() == dm.multiprocessing_context
    dm.multiprocessing_context = "Fork"  # settable, checked
    assert dm.test_dataloader().multiprocessing_context.get_start_method() == "fork"
    with pytest.raises(ValueError, match=r"dataset\.multiprocessing_context must be"):
        dm.multiprocessing_context = "vfork"


@pytest.mark.parametrize("config", ["modelnet10", "pascal3d", "symsol1", "symsol_rendered"])
def test_dataset_configs_leave_the_start_method_to_the_default(config):
    cfg = OmegaConf.load(REPO / "conf" / "dataset" / f"{config}.yaml")
    assert "multiprocessing_context" in cfg and cfg.multiprocessing_context is None


# ------------------------------------------------------------------------------ datasets through pickle


def assert_same_item(got: dict | None, expected: dict | None) -> None:
    assert (got is None) == (expected is None)
    assert set(got) == set(expected)
    for key in expected:
        torch.testing.assert_close(got[key], expected[key], rtol=0, atol=0, msg=lambda m, key=key: f"{key}: {m}")


@pytest.mark.parametrize("name", [*DATASETS, "symsol_cached"])
def test_every_dataset_survives_pickling_and_gives_the_same_items(roots, name):
    """What a forkserver or spawn worker receives: the dataset pickled (here with plain pickle, which copies
    tensors; the workers' pickler shares them). ``symsol_cached`` is the built-in rendered set's reader."""
    dm = make_datamodule("symsol" if name == "symsol_cached" else name, roots,
                         **({"cache_images": True} if name == "symsol_cached" else {}))  # fmt: skip
    for data in (dm.data_train, dm.data_test):
        data[0]  # ModelNet10: the LMDB environment is open in this process now
        copy = pickle.loads(pickle.dumps(data))
        assert type(copy) is type(data) and len(copy) == len(data)
        if name == "modelnet10":
            assert copy._env is None  # opened again on the first read, in the process that reads
        keys = [0, len(data) - 1] + (
            [EpochIndex(2, 1), EpochIndex(5, len(data) - 1)] if hasattr(data, "set_epoch") else []
        )
        for key in keys:
            assert_same_item(copy[key], data[key])


def timed(fn, *args) -> float:
    t0 = time.perf_counter()
    fn(*args)
    return time.perf_counter() - t0


def test_synthetic_views_are_the_views_and_pickle_small():
    views = [SyntheticView(Path(f"/data/syn/02691156/{i:032x}/02691156_{i:032x}_a{i % 360:03d}_e010_t-02_d003.png"),
                           i % 12, i % 360, 10, -2) for i in range(20000)]  # fmt: skip
    packed = SyntheticViews(views)
    assert len(packed) == 20000 and list(packed) == views and packed[-1] == views[-1] and packed[3:5] == views[3:5]
    with pytest.raises(IndexError):
        packed[20000]
    copy = pickle.loads(pickle.dumps(packed))
    assert list(copy) == views
    # no object per view in the pickle (the list's holds a SyntheticView and a PosixPath per view), so
    # unpickling is a few copies; the workers' pickler shares the tensors instead of copying them
    assert b"pascal3d_annotations" in pickle.dumps(views) and b"pascal3d_annotations" not in pickle.dumps(packed)
    assert b"PosixPath" not in pickle.dumps(packed)

    def load_time(obj) -> float:
        data = pickle.dumps(obj)
        return min(timed(pickle.loads, data) for _ in range(3))

    assert load_time(packed) < 0.5 * load_time(views)
    assert len(SyntheticViews()) == 0 and list(SyntheticViews([])) == []


# ------------------------------------------------------------------- signals of workers of a fork server


def group_left(pgid: int, seconds: float = 5.0) -> list[str]:
    """The command lines of the processes of group ``pgid`` still alive after up to ``seconds``."""
    deadline = time.monotonic() + seconds
    while group_alive(pgid) and time.monotonic() < deadline:
        time.sleep(0.05)
    left = []
    for pid in group_alive(pgid):
        try:
            left.append(Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()[:200])
        except OSError:
            pass
    return left


FORKSERVER_SCRIPT = """
import os, signal, subprocess, sys, time
import torch
from torch.utils.data import DataLoader, Dataset
from image2sphere.data.workers import init_worker, worker_context


class Slow(Dataset):
    def __len__(self):
        return 1000

    def __getitem__(self, i):
        time.sleep(0.005)
        return torch.tensor([i])


if __name__ == "__main__":
    loader = DataLoader(Slow(), batch_size=2, num_workers=1, persistent_workers=True, worker_init_fn=init_worker,
                        multiprocessing_context=worker_context())
    it = iter(loader)
    next(it)
    (worker,) = [w.pid for w in it._workers]
    from multiprocessing import forkserver
    server = forkserver._forkserver._forkserver_pid
    print("worker", worker, "server", server, flush=True)
    if sys.argv[1] == "kill-rank":
        time.sleep(600)  # killed by the test
    subprocess.run(["kill", "-TERM", str(worker)], check=True)  # from another process: left to the rank
    subprocess.run(["kill", "-INT", str(worker)], check=True)
    got = []
    signal.signal(signal.SIGTERM, lambda *_: got.append(1))  # the rank records it (image2sphere.training.stop)
    group = os.getpgid(0)
    subprocess.run(["kill", "-TERM", "--", f"-{group}"], check=True, start_new_session=True)  # the whole job
    time.sleep(0.5)
    batches = [next(it)[0, 0].item() for _ in range(5)]
    print("served", batches, "rank got", got, "server alive", os.path.exists(f"/proc/{server}/stat"), flush=True)
    # the script ends with the persistent worker alive: Python's multiprocessing terminates it at exit (SIGTERM
    # from this process, which is not the worker's parent here), which the worker must obey; the fork server
    # then ends
"""


@pytest.mark.slow
def test_forkserver_workers_ignore_signals_from_outside_and_obey_their_ranks_terminate(tmp_path):
    """The variant of tests/test_stop.py's test for the default start method, whose workers are children
    of the fork server, not of their rank: a SIGTERM or Ctrl-C from another process is ignored, as is a
    SIGTERM to the whole process group (by the fork server too, which the workers need); the rank's
    terminate at exit ends the worker, and nothing of the group is left."""
    script = tmp_path / "forkserver_rank.py"
    script.write_text(FORKSERVER_SCRIPT)
    with process_group([sys.executable, str(script), "signals"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                       text=True) as proc:  # fmt: skip
        out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err[-3000:]
    worker, server = int(out.split("worker ")[1].split()[0]), int(out.split("server ")[1].split()[0])
    assert "served [2, 4, 6, 8, 10] rank got [1] server alive True" in out, out + err[-2000:]
    assert not group_left(proc.pid)  # the fork server and resource tracker end just after the rank's output
    assert not set(group_alive(proc.pid)) & {worker, server}  # ended (a zombie at most, once reparented)


@pytest.mark.slow
def test_forkserver_workers_end_with_a_killed_rank(tmp_path):
    """A rank killed with SIGKILL leaves neither its workers (whose parent, the fork server, lives on) nor
    the fork server behind."""
    script = tmp_path / "forkserver_rank.py"
    script.write_text(FORKSERVER_SCRIPT)
    with process_group([sys.executable, str(script), "kill-rank"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                       text=True) as proc:  # fmt: skip
        line = proc.stdout.readline()
        assert line.startswith("worker "), line + proc.stderr.read()[-3000:]
        worker, server = int(line.split()[1]), int(line.split()[3])
        assert parent_of(worker) == server != proc.pid
        proc.kill()
        proc.wait()
        assert not group_left(proc.pid, 20)
