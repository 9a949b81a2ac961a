"""Every DataModule with DataLoader workers: the same items in the same order as without workers
(fork and spawn), the epoch reaching persistent workers, resume within an epoch, LMDB environments
per worker, and the ``num_workers`` / ``pin_memory`` settings.

The datasets are the published-layout fixtures of :mod:`image2sphere.data.fixtures`.
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import lightning.pytorch as pl
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from image2sphere.data import common, modelnet
from image2sphere.data.fixtures.modelnet10 import write_modelnet10
from image2sphere.data.fixtures.pascal3d import write_pascal3d, write_renderforcnn
from image2sphere.data.fixtures.symsol import write_symsol
from image2sphere.data.loading import EpochIndex, EpochShuffleSampler
from image2sphere.data.modelnet import ModelNet10DataModule, ModelNet10Dataset, close_lmdb_environments
from image2sphere.data.pascal3d import Pascal3DDataModule
from image2sphere.data.symsol import SymsolDataModule
from image2sphere.data.workers import auto_num_workers, check_num_workers, init_worker, local_processes

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


@pytest.mark.parametrize("name", DATASETS)
def test_two_workers_give_the_items_of_zero_workers(roots, name):
    reference = make_datamodule(name, roots, num_workers=0)
    dm = make_datamodule(name, roots, num_workers=2)
    for make in ("train_dataloader", "test_dataloader"):
        zero, two = getattr(reference, make)(), getattr(dm, make)()
        assert zero.num_workers == 0 and not zero.persistent_workers
        assert two.num_workers == 2 and two.persistent_workers and two.worker_init_fn is init_worker
        epoch = 0 if make == "train_dataloader" else None
        expected = epoch_batches(zero, epoch)
        assert_same_batches(epoch_batches(two, epoch), expected)
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
    dm = make_datamodule("modelnet10", roots, num_workers=2)  # the constructor opened both splits' LMDBs here
    assert len(modelnet._ENVIRONMENTS) == 2
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
