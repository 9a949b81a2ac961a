"""The SYMSOL reader and data module on small sets written in the published layout."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from conftest import haar_rotations
from image2sphere.data.common import CorruptImageError, DatasetNotFoundError, normalize_images
from image2sphere.data.datamodule import SymsolDataModule
from image2sphere.data.fixtures.symsol import write_symsol
from image2sphere.data.loading import EpochShuffleSampler, collate_skipping_corrupt
from image2sphere.data.symsol import SymsolDataset
from image2sphere.data.symsol_labels import load_symsol_rotations
from image2sphere.data.verify import verify_symsol

SIZE = 16


def _write_split(root, split: str, sets: dict[str, np.ndarray], seed: int = 0) -> None:
    """Images (random colours) and rotations.npz for ``sets[shape]`` of shape (N, M, 3, 3) or object."""
    rng = np.random.default_rng(seed)
    (root / split / "images").mkdir(parents=True)
    for shape, rotations in sets.items():
        for i in range(len(rotations)):
            pixels = rng.integers(0, 256, (SIZE, SIZE, 3), dtype=np.uint8)
            Image.fromarray(pixels).save(root / split / "images" / f"{shape}_{i:05d}.png")
    np.savez(root / split / "rotations.npz", **sets)


def _equivalents(n: int, m: int, seed: int) -> np.ndarray:
    """(n, m, 3, 3): each row R @ S_j for m random S_j (S_0 = identity)."""
    R = haar_rotations(n, seed=seed)
    S = haar_rotations(m, seed=seed + 100)
    S[0] = torch.eye(3, dtype=S.dtype)
    return (R[:, None] @ S[None]).numpy().astype(np.float32)


@pytest.fixture
def symsol_root(tmp_path):
    """cube: dense (N, 24); tetX: NaN-padded with M in {1, 3, 6}; train 10 and test 4 per shape."""
    root = tmp_path / "symsol"
    for split, n, seed in (("train", 10, 0), ("test", 4, 50)):
        cube = _equivalents(n, 24, seed)
        tetx = _equivalents(n, 6, seed + 1)
        counts = np.resize([1, 3, 6], n)
        for i, c in enumerate(counts):
            tetx[i, c:] = np.nan
        _write_split(root, split, {"cube": cube, "tetX": tetx}, seed)
    return root


def test_loader_compacts_nan_padding_and_reads_object_arrays(symsol_root, tmp_path):
    rot = load_symsol_rotations(symsol_root / "train", ["cube", "tetX"])
    cube, cube_counts = rot["cube"]
    tetx, tetx_counts = rot["tetX"]
    assert cube.shape == (10, 24, 3, 3) and (cube_counts == 24).all()
    assert tetx.shape == (10, 6, 3, 3) and tetx_counts.tolist() == np.resize([1, 3, 6], 10).tolist()
    assert np.isfinite(tetx).all()  # padding replaced by the first rotation
    # the same rotations as an object array (variable M per image)
    raw = np.load(symsol_root / "train" / "rotations.npz")["tetX"]
    obj = np.empty(10, dtype=object)
    for i, c in enumerate(tetx_counts):
        obj[i] = raw[i, :c]
    other = tmp_path / "obj"
    _write_split(other, "train", {"tetX": obj})
    dense, counts = load_symsol_rotations(other / "train", ["tetX"])["tetX"]
    np.testing.assert_array_equal(counts, tetx_counts)
    for i, c in enumerate(counts):
        np.testing.assert_array_equal(dense[i, :c], raw[i, :c])


def test_loader_errors_name_the_file_and_key(symsol_root, tmp_path):
    with pytest.raises(ValueError, match=r"rotations.npz has no key 'cone'"):
        load_symsol_rotations(symsol_root / "train", ["cone"])
    with pytest.raises(FileNotFoundError, match="rotations.npz"):
        load_symsol_rotations(tmp_path / "nowhere", ["cube"])
    bad = _equivalents(3, 2, 0)
    bad[1, 0] *= 2.0  # not orthonormal
    _write_split(tmp_path / "bad", "train", {"cube": bad})
    with pytest.raises(ValueError, match=r"\['cube'\]: rows \[1\] are not rotation matrices"):
        load_symsol_rotations(tmp_path / "bad" / "train", ["cube"])


def test_dataset_items_and_label_in_equivalent_set(symsol_root):
    ds = SymsolDataset(symsol_root, "train", ["cube", "tetX"], label="random", image_size=SIZE)
    assert len(ds) == 20
    item = ds[13]  # tetX row 3: M = 1
    assert item["image"].shape == (3, SIZE, SIZE) and item["image"].dtype == torch.float32
    assert item["class_index"].item() == 1 and item["index"].item() == 3
    raw = np.load(symsol_root / "train" / "rotations.npz")
    # random labels are members of the set, vary over epochs and are reproducible
    chosen = []
    for epoch in range(8):
        ds.set_epoch(epoch)
        label = ds[2]["rotation"].numpy()  # cube row 2
        assert np.abs(raw["cube"][2] - label).reshape(24, -1).max(1).min() == 0
        chosen.append(label)
    assert len({a.tobytes() for a in chosen}) > 1
    ds.set_epoch(3)
    np.testing.assert_array_equal(ds[2]["rotation"].numpy(), chosen[3])
    first = SymsolDataset(symsol_root, "train", ["cube"], label="first", image_size=SIZE)
    np.testing.assert_array_equal(first[2]["rotation"].numpy(), raw["cube"][2, 0])
    # the image is the file, normalised
    png = np.array(Image.open(symsol_root / "train" / "images" / "tetX_00003.png"))
    torch.testing.assert_close(item["image"], normalize_images(torch.from_numpy(png)))


def test_label_all_gives_training_items_their_full_equivalent_set(symsol_root):
    """dataset.label=all: training items carry every equivalent rotation with a mask (as evaluation
    items do) and no single label, the same for every epoch; the data module's training batches too."""
    ds = SymsolDataset(symsol_root, "train", ["cube", "tetX"], label="all", image_size=SIZE)
    raw = np.load(symsol_root / "train" / "rotations.npz")
    item = ds[14]  # tetX row 4: M = 3
    assert "rotation" not in item and item["mask"].sum() == 3 and item["mask"][:3].all()
    np.testing.assert_array_equal(item["rotations"][:3].numpy(), raw["tetX"][4, :3])
    ds.set_epoch(5)
    np.testing.assert_array_equal(ds[14]["rotations"].numpy(), item["rotations"].numpy())
    assert ds[2]["mask"].all() and ds[2]["rotations"].shape == (24, 3, 3)  # cube: 24 of 24
    dm = SymsolDataModule(
        root=str(symsol_root), shapes=["cube", "tetX"], val_per_shape=2, image_size=8, batch_size=4,
        label="all", cache_images=True,
    )  # fmt: skip
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    assert batch["rotations"].shape == (4, 24, 3, 3) and batch["mask"].shape == (4, 24)
    with pytest.raises(ValueError, match="dataset.label must be one of"):
        SymsolDataModule(root=str(symsol_root), shapes=["cube"], label="every")


def test_eval_items_hold_full_set_with_mask(symsol_root):
    ds = SymsolDataset(symsol_root, "test", ["tetX", "cube"], return_all=True, image_size=SIZE)
    raw = np.load(symsol_root / "test" / "rotations.npz")
    item = ds[1]  # tetX row 1: M = 3
    assert item["rotations"].shape == (24, 3, 3) and item["mask"].shape == (24,)
    assert item["mask"].sum() == 3 and item["mask"][:3].all()
    np.testing.assert_array_equal(item["rotations"][:3].numpy(), raw["tetX"][1, :3])
    assert torch.isfinite(item["rotations"]).all()
    assert ds[5]["mask"].all()  # cube: 24 of 24


def test_datamodule_split_counts_loaders_and_resize(symsol_root):
    dm = SymsolDataModule(
        root=str(symsol_root), shapes=["cube", "tetX"], val_per_shape=3, test_per_shape=2,
        image_size=8, batch_size=4, cache_images=True, seed=5,
    )  # fmt: skip
    dm.prepare_data()
    dm.setup("fit")
    dm.setup("test")
    assert len(dm.data_train) == 14 and len(dm.data_val) == 6 and len(dm.data_test) == 4
    train_rows = {(c, r) for c, r in dm.data_train.items}
    val_rows = {(c, r) for c, r in dm.data_val.items}
    assert not train_rows & val_rows and len(train_rows | val_rows) == 20
    batch = next(iter(dm.train_dataloader()))
    assert batch["image"].shape == (4, 3, 8, 8) and batch["rotation"].shape == (4, 3, 3)
    assert batch["class_index"].dtype == torch.int64
    test_batches = list(dm.test_dataloader())
    assert sum(len(b["image"]) for b in test_batches) == 4  # every test image, no dropped batch
    assert test_batches[0]["rotations"].shape[1:] == (24, 3, 3)
    assert dm.class_names == ["cube", "tetX"]


def test_shuffle_depends_only_on_seed_and_epoch():
    a, b = EpochShuffleSampler(50, seed=1), EpochShuffleSampler(50, seed=1)
    a.set_epoch(4)
    b.set_epoch(4)
    assert list(a) == list(b) and sorted(a) == list(range(50))
    b.set_epoch(5)
    assert list(a) != list(b)


def test_datamodule_config_errors(symsol_root, tmp_path):
    with pytest.raises(ValueError, match="dataset.shapes"):
        SymsolDataModule(root=str(symsol_root), shapes=["cube", "dodecahedron"])
    with pytest.raises(ValueError, match="dataset.root is not set"):
        SymsolDataModule(root=None)
    with pytest.raises(DatasetNotFoundError, match=r"SYMSOL not found at .*missing: expected .*symsol_dataset.zip"):
        SymsolDataModule(root=str(tmp_path / "missing"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetNotFoundError, match=r"missing: train/rotations.npz, test/rotations.npz"):
        SymsolDataModule(root=str(tmp_path / "empty"))
    with pytest.raises(ValueError, match=r"dataset.shape='cylO' and dataset.shapes=\['cube'\] disagree"):
        SymsolDataModule(root=str(symsol_root), shapes=["cube"], shape="cylO")
    with pytest.raises(ValueError, match="dataset.on_corrupt"):
        SymsolDataModule(root=str(symsol_root), on_corrupt="ignore")
    dm = SymsolDataModule(root=str(symsol_root), shapes=["cube"], val_per_shape=10)
    with pytest.raises(ValueError, match="val_per_shape=10 leaves no training images"):
        dm.setup("fit")
    png = (symsol_root / "train" / "images" / "cube_00004.png").read_bytes()
    (symsol_root / "train" / "images" / "cube_00004.png").write_bytes(png[: len(png) // 2])  # truncated
    ds = SymsolDataset(symsol_root, "train", ["cube"], image_size=SIZE)
    with pytest.raises(CorruptImageError, match="cube_00004.png"):
        ds[4]
    skipping = SymsolDataset(symsol_root, "train", ["cube"], image_size=SIZE, on_corrupt="skip")
    batch = collate_skipping_corrupt([skipping[i] for i in range(len(skipping))])
    assert int(batch["skipped"]) == 1 and len(batch["image"]) == len(skipping) - 1
    assert collate_skipping_corrupt([skipping[4]]) is None
    (symsol_root / "train" / "images" / "cube_00004.png").unlink()
    with pytest.raises(FileNotFoundError, match="cube_00004.png"):
        SymsolDataset(symsol_root, "train", ["cube"], image_size=SIZE)


def test_published_layout_fixture_reads_back_every_shape(tmp_path):
    """Dense (unmarked), object-array (tetX, sphereX) and NaN-padded (cylO) sets, read exactly."""
    truth = write_symsol(tmp_path / "symsol", per_split={"train": 6, "test": 3})
    rotations = load_symsol_rotations(tmp_path / "symsol" / "test", list(truth["test"]))
    for shape, sets in truth["test"].items():
        dense, counts = rotations[shape]
        assert counts.tolist() == [len(s) for s in sets]
        for i, s in enumerate(sets):
            np.testing.assert_allclose(dense[i, : counts[i]], s, atol=1e-6)
    assert {len(s) for s in truth["test"]["cube"]} == {24} and len(set(map(len, truth["train"]["tetX"]))) > 1
    with np.load(tmp_path / "symsol" / "test" / "rotations.npz", allow_pickle=True) as archive:
        assert archive["tetX"].dtype == object and archive["cylO"].dtype == np.float32

    dm = SymsolDataModule(root=str(tmp_path / "symsol"), shape="cylO", shapes=None, num_views=4, val_per_shape=1,
                          image_size=SIZE, batch_size=8)  # fmt: skip
    dm.setup()
    assert dm.class_names == ["cylO"] and len(dm.data_train) == 3 and len(dm.data_val) == 1
    assert len(dm.data_test) == 3
    batch = next(iter(dm.test_dataloader()))
    assert batch["rotations"].shape[:2] == batch["mask"].shape and int(batch["skipped"]) == 0
    assert batch["mask"].sum(1).tolist() == [len(s) for s in truth["test"]["cylO"]]


def test_verify_counts_against_the_release_and_lists_unreadable_images(tmp_path):
    root = tmp_path / "symsol"
    write_symsol(root, shapes=("cube", "tetX"), per_split={"train": 4, "test": 2})
    report = verify_symsol(root, progress=False)
    assert ("train", "cube", 4, 45000) in report.counts and ("test", "tetX", 2, 5000) in report.counts
    assert not report.ok and len(report.mismatches) == 4 and not report.unreadable
    (root / "test" / "images" / "tetX_00001.png").write_bytes(b"\x89PNG broken")
    (root / "train" / "images" / "cube_00003.png").unlink()
    report = verify_symsol(root, progress=False)
    assert report.unreadable == [str(root / "test" / "images" / "tetX_00001.png")]
    assert report.problems == [f"missing image {root / 'train' / 'images' / 'cube_00003.png'}"]
    assert "FAILED" in report.format()


def test_rendered_cache_folder_names_every_parameter_and_the_renderer_version(tmp_path, monkeypatch):
    """A set rendered with other parameters, or by another renderer version, lands in another folder:
    an old cache is never reused for a different set (nor refused, nor deleted)."""
    import image2sphere.data.render as render_module

    def root(**render):
        spec = {"train": 8, "test": 4, "image_size": 32, "seed": 0, **render}
        return SymsolDataModule(root=None, render=spec, render_dir=str(tmp_path), shapes=["cube"], image_size=32).root

    base = root()
    assert (
        base.parent == tmp_path
        and base.name == f"cube_32px_train8_test4_seed0_renderer{render_module.RENDERER_VERSION}"
    )
    assert root(supersample=3) != base and "supersample3" in root(supersample=3).name
    assert root(seed=1) != base and root(train=9) != base
    assert root(batch_size=2, progress=False) == base  # how it is rendered, not what
    monkeypatch.setattr(render_module, "RENDERER_VERSION", render_module.RENDERER_VERSION + 1)
    assert root() != base
