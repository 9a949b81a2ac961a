"""The ModelNet10-SO(3) reader, data module and verify on small sets written in the published layout."""

from __future__ import annotations

import io
import logging
import math
import pickle
import re
import shutil

import lmdb
import numpy as np
import pytest
import torch
from PIL import Image
from torch.utils.data import DataLoader, Subset

from image2sphere.data import modelnet
from image2sphere.data.common import IMAGENET_MEAN, IMAGENET_STD, CorruptImageError, DatasetNotFoundError
from image2sphere.data.datamodule import ModelNet10DataModule
from image2sphere.data.fixtures.modelnet10 import corrupt_modelnet10_record, write_modelnet10
from image2sphere.data.loading import collate_skipping_corrupt
from image2sphere.data.modelnet import MissingRecordError, ModelNet10Dataset, close_lmdb_environments
from image2sphere.data.modelnet_labels import (
    MODELNET10_CLASSES,
    load_modelnet10_labels,
    parse_view_id,
    quaternion_wxyz_to_matrix,
)
from image2sphere.data.verify import verify_modelnet10

URL = "http://isis-data.science.uva.nl/shuai/datasets/ModelNet10-SO3.tar.gz"
VIEWS = {"train_100V": 3, "train_20V": 2, "test_20V": 2}


@pytest.fixture(autouse=True)
def _close_environments():
    """The reader keeps one LMDB environment per path and process; release them after every test."""
    yield
    close_lmdb_environments()


@pytest.fixture
def root(tmp_path):
    """All ten classes, 2 instances each, views as in VIEWS, 32x32 images; returns (root, truth)."""
    path = tmp_path / "ModelNet10-SO3"
    truth = write_modelnet10(path, instances_per_class=2, views=VIEWS, image_size=32, seed=0)
    return path, truth


def _raw_record(root, split: str, key: str) -> bytes:
    """The stored bytes of one record, read with lmdb directly (not through the reader)."""
    close_lmdb_environments()
    env = lmdb.open(str(root / f"{split}.Rawjpg.lmdb"), readonly=True, lock=False)
    try:
        with env.begin() as txn:
            return bytes(txn.get(key.encode()))
    finally:
        env.close()


def _rewrite_pkl(root, split: str, edit) -> None:
    path = root / f"{split}.Rawjpg.lmdb" / "viewID2quat.pkl"
    with open(path, "rb") as f:
        quats = pickle.load(f, encoding="latin1")
    quats = edit(quats)
    with open(path, "wb") as f:
        pickle.dump(quats, f, protocol=2)


def _unnormalize(image: torch.Tensor) -> np.ndarray:
    """float32 (3, H, W) ImageNet-normalised -> float (H, W, 3) on the 0..255 scale."""
    mean = torch.tensor(IMAGENET_MEAN)[:, None, None]
    std = torch.tensor(IMAGENET_STD)[:, None, None]
    return ((image * std + mean) * 255).permute(1, 2, 0).double().numpy()


# ---------------------------------------------------------------------------------------------
# reading the fixture back


def test_fixture_reads_back_counts_classes_and_rotations(root):
    path, truth = root
    for split, n_views in VIEWS.items():
        ds = ModelNet10Dataset(path, split)
        assert len(ds) == len(truth[split]) == 10 * 2 * n_views
        assert ds.labels.keys == sorted(truth[split])
        counts = np.bincount(ds.labels.class_index, minlength=10)
        assert counts.tolist() == [2 * n_views] * 10
        for row, key in enumerate(ds.labels.keys):
            cls = key.rsplit("_", 1)[0]
            assert ds.labels.class_index[row] == MODELNET10_CLASSES.index(cls)
            np.testing.assert_allclose(ds.labels.rotations[row], truth[split][key], atol=1e-5)
        stands = [r for r, k in enumerate(ds.labels.keys) if k.startswith("night_stand_")]
        assert len(stands) == 2 * n_views
        assert {int(ds.labels.class_index[r]) for r in stands} == {MODELNET10_CLASSES.index("night_stand")}
        assert {ds.labels.instances[r] for r in stands} == {
            k.split(".")[0] for k in truth[split] if k.startswith("night_stand_")
        }
        # items carry the same labels
        for i in (0, len(ds) // 2, len(ds) - 1):
            item = ds[i]
            key = ds.labels.keys[i]
            assert set(item) == {"image", "class_index", "index", "rotation"}
            assert item["index"].dtype == torch.int64 and int(item["index"]) == i
            assert item["class_index"].dtype == torch.int64
            assert int(item["class_index"]) == MODELNET10_CLASSES.index(key.rsplit("_", 1)[0])
            assert item["rotation"].dtype == torch.float32 and item["rotation"].shape == (3, 3)
            np.testing.assert_allclose(item["rotation"].numpy(), truth[split][key], atol=1e-5)
    # test instances are numbered after the training ones, as in ModelNet10
    assert parse_view_id(min(truth["test_20V"])) == ("bathtub", "bathtub_0003")


def test_view_id_parsing():
    assert parse_view_id("night_stand_0012.v003") == ("night_stand", "night_stand_0012")
    assert parse_view_id("bathtub_0107.v001") == ("bathtub", "bathtub_0107")
    for bad in ("bathtub0107.v001", "bathtub_0107", "_0107.v001"):
        with pytest.raises(ValueError, match="view id"):
            parse_view_id(bad)


def test_images_are_the_decoded_jpeg_with_equal_channels(root):
    path, truth = root
    key = sorted(truth["train_100V"])[7]
    raw = _raw_record(path, "train_100V", key)
    decoded = np.asarray(Image.open(io.BytesIO(raw)).convert("RGB"), dtype=np.float64)
    assert decoded.shape == (32, 32, 3)

    ds = ModelNet10Dataset(path, "train_100V", image_size=32)
    item = ds[ds.labels.keys.index(key)]
    assert item["image"].dtype == torch.float32 and item["image"].shape == (3, 32, 32)
    restored = _unnormalize(item["image"])
    np.testing.assert_allclose(restored, decoded, atol=1e-3)
    np.testing.assert_allclose(restored[..., 0], restored[..., 1], atol=1e-3)
    np.testing.assert_allclose(restored[..., 0], restored[..., 2], atol=1e-3)
    assert restored.max() - restored.min() > 100  # a bright square on a dark background, not blank

    small = ModelNet10Dataset(path, "train_100V", image_size=16)[ds.labels.keys.index(key)]["image"]
    assert small.shape == (3, 16, 16)
    restored = _unnormalize(small)
    np.testing.assert_allclose(restored[..., 0], restored[..., 2], atol=1e-3)
    expected = np.asarray(Image.open(io.BytesIO(raw)).convert("RGB").resize((16, 16), Image.Resampling.BILINEAR))
    assert np.abs(restored - expected).max() < 2


# ---------------------------------------------------------------------------------------------
# quaternion convention


def test_quaternion_convention_by_hand():
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    np.testing.assert_allclose(
        quaternion_wxyz_to_matrix(np.array([c, 0, 0, s])), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12
    )
    np.testing.assert_allclose(quaternion_wxyz_to_matrix(np.array([0.0, 1, 0, 0])), np.diag([1, -1, -1]), atol=1e-12)
    np.testing.assert_allclose(quaternion_wxyz_to_matrix(np.array([2.0, 0, 0, 0])), np.eye(3), atol=1e-12)

    q = np.random.default_rng(0).normal(size=(2, 5, 4))
    R = quaternion_wxyz_to_matrix(q)
    assert R.shape == (2, 5, 3, 3)
    np.testing.assert_allclose(quaternion_wxyz_to_matrix(-q), R, atol=1e-12)
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1, atol=1e-12)
    for shape in ((3,), (2, 3), ()):
        with pytest.raises(ValueError, match=re.escape(str(shape))):
            quaternion_wxyz_to_matrix(np.zeros(shape))


def test_reader_uses_the_stored_quaternion_without_transpose(root):
    """A 90 degree turn about z stored as (w, x, y, z): the item's rotation is the hand-computed matrix."""
    path, truth = root
    key = sorted(truth["test_20V"])[0]
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)

    def edit(quats):
        quats[key] = (-c, 0.0, 0.0, -s)  # a tuple, sign flipped
        quats[sorted(quats)[1]] = [0.0, 1.0, 0.0, 0.0]  # a list
        return quats

    _rewrite_pkl(path, "test_20V", edit)
    ds = ModelNet10Dataset(path, "test_20V", return_all=True)
    item = ds[0]
    np.testing.assert_allclose(item["rotations"][0].numpy(), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-6)
    np.testing.assert_allclose(ds[1]["rotations"][0].numpy(), np.diag([1.0, -1.0, -1.0]), atol=1e-6)
    np.testing.assert_allclose(ds[2]["rotations"][0].numpy(), truth["test_20V"][ds.labels.keys[2]], atol=1e-5)


def test_bytes_keys_as_in_some_python2_pickles_are_accepted(root):
    path, truth = root
    _rewrite_pkl(path, "test_20V", lambda q: {k.encode(): tuple(v.tolist()) for k, v in q.items()})
    labels = load_modelnet10_labels(path / "test_20V.Rawjpg.lmdb")
    assert labels.keys == sorted(truth["test_20V"])
    np.testing.assert_allclose(labels.rotations, np.stack([truth["test_20V"][k] for k in labels.keys]), atol=1e-5)


def test_bad_quaternion_norm_is_rejected_naming_file_and_key(root):
    path, truth = root
    keys = sorted(truth["train_20V"])
    bad, slightly_off = keys[5], keys[6]

    def edit(quats):
        quats[bad] = quats[bad] * 1.01
        quats[slightly_off] = quats[slightly_off] * (1 + 5e-4)
        return quats

    _rewrite_pkl(path, "train_20V", edit)
    directory = path / "train_20V.Rawjpg.lmdb"
    with pytest.raises(ValueError, match=re.escape(bad)) as info:
        load_modelnet10_labels(directory)
    assert str(directory / "viewID2quat.pkl") in str(info.value)
    assert slightly_off not in str(info.value)  # within 1e-3: accepted

    _rewrite_pkl(path, "train_20V", lambda q: {**q, bad: q[bad] / 1.01})
    labels = load_modelnet10_labels(directory)
    R = labels.rotations[labels.keys.index(slightly_off)].astype(np.float64)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)  # normalised
    np.testing.assert_allclose(R, truth["train_20V"][slightly_off], atol=1e-5)


def test_wrong_length_quaternion_and_unknown_class_name_the_key(root):
    path, _ = root
    _rewrite_pkl(path, "test_20V", lambda q: {**q, "bed_0003.v001": np.zeros(3)})
    with pytest.raises(ValueError, match=r"bed_0003\.v001"):
        load_modelnet10_labels(path / "test_20V.Rawjpg.lmdb")
    _rewrite_pkl(
        path, "test_20V", lambda q: {**q, "bed_0003.v001": np.array([1.0, 0, 0, 0]), "lamp_0001.v001": (1, 0, 0, 0)}
    )
    with pytest.raises(ValueError, match=r"lamp_0001\.v001.*unknown class 'lamp'"):
        load_modelnet10_labels(path / "test_20V.Rawjpg.lmdb")


# ---------------------------------------------------------------------------------------------
# the data module


def test_datamodule_splits_validation_by_instance(tmp_path):
    path = tmp_path / "ModelNet10-SO3"
    write_modelnet10(path, instances_per_class=3, views=VIEWS, image_size=16)
    dm = ModelNet10DataModule(path, val_instances_per_class=1, image_size=16, batch_size=8, seed=3)
    assert dm.class_names == list(MODELNET10_CLASSES)
    dm.setup("fit")
    labels = dm.data_train.labels
    train_instances = {labels.instances[r] for r in dm.data_train.rows}
    val_instances = {labels.instances[r] for r in dm.data_val.rows}
    assert not train_instances & val_instances
    assert len(train_instances) == 20 and len(val_instances) == 10
    assert len(dm.data_train) == 20 * 3 and len(dm.data_val) == 10 * 3
    assert np.bincount(labels.class_index[dm.data_val.rows], minlength=10).tolist() == [3] * 10
    assert sorted([*dm.data_train.rows, *dm.data_val.rows]) == list(range(len(labels)))
    val_item = dm.data_val[0]
    assert val_item["rotations"].shape == (1, 3, 3) and val_item["mask"].tolist() == [True]
    assert "rotation" in dm.data_train[0] and "rotations" not in dm.data_train[0]

    # the split depends on the seed only
    again = ModelNet10DataModule(path, val_instances_per_class=1, image_size=16, seed=3)
    again.setup("fit")
    assert again.data_val.rows.tolist() == dm.data_val.rows.tolist()
    other = ModelNet10DataModule(path, val_instances_per_class=1, image_size=16, seed=4)
    other.setup("fit")
    assert other.data_val.rows.tolist() != dm.data_val.rows.tolist()

    # loaders: one batch each
    batch = next(iter(dm.train_dataloader()))
    assert batch["image"].shape == (8, 3, 16, 16) and batch["rotation"].shape == (8, 3, 3)
    assert int(batch["skipped"]) == 0
    batch = next(iter(dm.val_dataloader()))
    assert batch["rotations"].shape == (8, 1, 3, 3) and batch["mask"].shape == (8, 1) and batch["mask"].all()
    dm.setup("test")
    assert len(dm.data_test) == 10 * 3 * VIEWS["test_20V"]
    loader = dm.test_dataloader()
    assert loader.drop_last is False and loader.collate_fn is collate_skipping_corrupt
    batch = next(iter(loader))
    assert batch["rotations"].shape == (8, 1, 3, 3) and batch["mask"].all()
    assert batch["index"].tolist() == list(range(8))  # evaluation is not shuffled
    assert sum(len(b["index"]) for b in loader) == len(dm.data_test)  # nothing dropped

    # the training order is a function of (seed, epoch)
    sampler = dm.train_dataloader().sampler
    order0 = list(sampler)
    assert list(sampler) == order0 and sorted(order0) == list(range(len(dm.data_train)))
    sampler.set_epoch(1)
    assert list(sampler) != order0
    assert list(again.train_dataloader().sampler) == order0

    with pytest.raises(ValueError, match="dataset.val_instances_per_class=3 leaves no training instances"):
        ModelNet10DataModule(path, val_instances_per_class=3).setup("fit")


def test_datamodule_limited_split(root):
    path, _ = root
    dm = ModelNet10DataModule(path, train_split="train_20V", image_size=16)
    dm.setup("fit")
    assert len(dm.data_train) == 10 * 2 * 2 and dm.data_val is None and dm.val_dataloader() == []


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [
        ({"train_split": "test_20V"}, "dataset.train_split"),
        ({"test_split": "test_4V"}, "dataset.test_split"),
        ({"val_instances_per_class": -1}, "dataset.val_instances_per_class"),
        ({"image_size": 0}, "dataset.image_size"),
        ({"batch_size": 0}, "dataset.batch_size"),
        ({"num_workers": -1}, "dataset.num_workers"),
        ({"pin_memory": "yes"}, "dataset.pin_memory"),
        ({"on_corrupt": "ignore"}, "dataset.on_corrupt"),
        ({"seed": 1.5}, "dataset.seed"),
        ({"root": None}, "dataset.root"),
    ],
)
def test_datamodule_validates_arguments(root, kwargs, key):
    path, _ = root
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        ModelNet10DataModule(**{"root": path, **kwargs})


# ---------------------------------------------------------------------------------------------
# missing and broken data


def test_missing_root_names_path_expectation_url_and_key(tmp_path):
    missing = tmp_path / "nowhere"
    with pytest.raises(DatasetNotFoundError) as info:
        ModelNet10DataModule(missing)
    message = str(info.value)
    for part in (
        str(missing),
        "train_100V.Rawjpg.lmdb",
        "test_20V.Rawjpg.lmdb",
        "viewID2quat.pkl",
        URL,
        "dataset.root",
    ):
        assert part in message
    assert isinstance(info.value, FileNotFoundError)


def test_empty_folder_and_missing_pickle(root, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DatasetNotFoundError, match="missing") as info:
        ModelNet10DataModule(empty)
    assert str(empty / "train_100V.Rawjpg.lmdb" / "data.mdb") in str(info.value) and URL in str(info.value)

    path, _ = root
    with pytest.raises(DatasetNotFoundError, match="did you mean"):  # the parent of the dataset folder
        ModelNet10DataModule(path.parent)

    pkl = path / "test_20V.Rawjpg.lmdb" / "viewID2quat.pkl"
    pkl.unlink()
    with pytest.raises(DatasetNotFoundError) as info:
        ModelNet10DataModule(path)
    assert str(pkl) in str(info.value) and "dataset.root" in str(info.value)
    ModelNet10DataModule(path, test_split="train_20V")  # the other splits are complete


def test_empty_pickle_and_empty_lmdb_are_named(root):
    path, _ = root
    _rewrite_pkl(path, "train_20V", lambda q: {})
    dm = ModelNet10DataModule(path, train_split="train_20V")
    with pytest.raises(ValueError, match="lists no views") as info:
        dm.setup("fit")
    assert str(path / "train_20V.Rawjpg.lmdb" / "viewID2quat.pkl") in str(info.value)

    directory = path / "test_20V.Rawjpg.lmdb"
    close_lmdb_environments()
    for name in ("data.mdb", "lock.mdb"):
        (directory / name).unlink()
    lmdb.open(str(directory), map_size=1 << 20).close()
    with pytest.raises(ValueError, match="empty LMDB") as info:
        ModelNet10DataModule(path)
    assert str(directory) in str(info.value)


def test_key_missing_from_lmdb_names_dir_and_key(root):
    path, _ = root
    ghost = "sofa_0003.v009"
    _rewrite_pkl(path, "test_20V", lambda q: {**q, ghost: np.array([1.0, 0, 0, 0])})
    ds = ModelNet10Dataset(path, "test_20V")
    with pytest.raises(MissingRecordError) as info:
        ds[ds.labels.keys.index(ghost)]
    assert str(path / "test_20V.Rawjpg.lmdb") in str(info.value) and ghost in str(info.value)


def test_truncated_jpeg_fails_or_is_skipped(root, caplog):
    path, truth = root
    keys = sorted(truth["test_20V"])
    broken = keys[1]
    corrupt_modelnet10_record(path, "test_20V", broken)
    name = f"{path / 'test_20V.Rawjpg.lmdb'}:{broken}"

    ds = ModelNet10Dataset(path, "test_20V", return_all=True)
    with pytest.raises(CorruptImageError) as info:
        ds[1]
    assert name in str(info.value) and info.value.source == name
    ds[0]  # the others still read

    skipping = ModelNet10Dataset(path, "test_20V", return_all=True, on_corrupt="skip")
    with caplog.at_level(logging.WARNING, logger=modelnet.__name__):
        assert skipping[1] is None and skipping[1] is None
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING and name in r.getMessage()]
    assert len(warnings) == 1
    batch = next(iter(DataLoader(Subset(skipping, range(4)), batch_size=4, collate_fn=collate_skipping_corrupt)))
    assert int(batch["skipped"]) == 1 and batch["index"].tolist() == [0, 2, 3]

    dm = ModelNet10DataModule(path, on_corrupt="skip", batch_size=len(keys), image_size=16)
    dm.setup("test")
    batches = list(dm.test_dataloader())
    assert len(batches) == 1 and int(batches[0]["skipped"]) == 1 and len(batches[0]["index"]) == len(keys) - 1


def test_worker_processes_open_their_own_environment(root, monkeypatch):
    path, truth = root
    ds = ModelNet10Dataset(path, "test_20V", image_size=16)
    first = ds[0]  # opens the environment in this process before the workers fork
    env = ds._env
    assert pickle.loads(pickle.dumps(ds))._env is None  # environments are not pickled

    loader = DataLoader(Subset(ds, range(8)), batch_size=4, num_workers=2, collate_fn=collate_skipping_corrupt)
    batches = list(loader)
    assert [b["index"].tolist() for b in batches] == [[0, 1, 2, 3], [4, 5, 6, 7]]
    torch.testing.assert_close(batches[0]["image"][0], first["image"])
    expected = np.stack([truth["test_20V"][ds.labels.keys[i]] for i in range(8)])
    np.testing.assert_allclose(torch.cat([b["rotation"] for b in batches]).numpy(), expected, atol=1e-5)
    assert ds._env is env  # the parent's environment is untouched

    # a process with another pid (what a forked worker is) opens a new environment
    monkeypatch.setattr(modelnet.os, "getpid", lambda: -12345)
    torch.testing.assert_close(ds[0]["image"], first["image"])
    assert ds._env is not env and ds._pid == -12345


# ---------------------------------------------------------------------------------------------
# verify


def test_verify_reports_counts_and_mismatches(root):
    path, _ = root
    report = verify_modelnet10(path, progress=False)
    assert not report.problems and not report.unreadable
    counts = {(s, c): (found, exp) for s, c, found, exp in report.counts}
    assert counts[("train_100V", "bathtub")] == (6, 106 * 100)
    assert counts[("train_100V", "night_stand")] == (6, 200 * 100)
    assert counts[("train_20V", "chair")] == (4, 889 * 20)
    assert counts[("test_20V", "desk")] == (4, None)
    assert counts[("test_20V (instances)", "desk")] == (2, 86)
    assert len(report.counts) == 10 * 4
    mismatched = {(s, c) for s, c, _, _ in report.mismatches}
    assert mismatched == {
        (s, c) for s in (*VIEWS, "test_20V (instances)") if s != "test_20V" for c in MODELNET10_CLASSES
    }
    assert not report.ok
    assert any("4 views per instance" in n and "found 2 views per instance" in n for n in report.notes)
    assert "FAILED" in report.format()


def test_verify_lists_unreadable_missing_and_extra_keys(root):
    path, truth = root
    broken = sorted(truth["train_20V"])[3]
    corrupt_modelnet10_record(path, "train_20V", broken)
    ghost, dropped = "bathtub_0001.v099", sorted(truth["train_100V"])[-1]

    def edit(quats):
        del quats[dropped]
        return {**quats, ghost: np.array([0.0, 0, 1, 0]), "lamp_0001.v001": np.array([1.0, 0, 0, 0])}

    _rewrite_pkl(path, "train_100V", edit)
    shutil.rmtree(path / "test_20V.Rawjpg.lmdb")
    report = verify_modelnet10(path, progress=False)
    assert report.unreadable == [f"{path / 'train_20V.Rawjpg.lmdb'}:{broken}"]
    problems = "\n".join(report.problems)
    assert "split test_20V is missing" in problems
    assert ghost in problems and "missing" in problems
    assert dropped in problems and "no quaternion" in problems
    assert "lamp_0001.v001" in problems and "unknown class" in problems
    assert "not uniform" in problems  # bathtub_0001 has 4 views, the others 3
    assert not report.ok

    report = verify_modelnet10(path, splits=("train_20V",), decode=False, progress=False)
    assert not report.unreadable and not report.problems
