"""PASCAL3D+ and RenderForCNN readers on fixtures written in the published layout, the rotation
conventions against hand-computed cases and the annotation tool's projection, and the warp and
flip augmentations against the label they produce."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from image2sphere.data.augment import GL_TO_CV, MIRROR_X, box_to_virtual_camera, hflip_image, hflip_rotation, warp_image
from image2sphere.data.common import CorruptImageError, DatasetNotFoundError
from image2sphere.data.datamodule import Pascal3DDataModule
from image2sphere.data.fixtures.pascal3d import (
    DOT_COLOURS,
    OBJECT_POINTS,
    camera_centre,
    project_like_annotation_tool,
    write_pascal3d,
    write_renderforcnn,
)
from image2sphere.data.loading import collate_skipping_corrupt
from image2sphere.data.pascal3d import Pascal3DDataset
from image2sphere.data.pascal3d_annotations import (
    list_pascal3d_objects,
    list_renderforcnn,
    parse_renderforcnn_name,
    pascal3d_rotation,
    read_pascal3d_annotation,
    renderforcnn_rotation,
)
from image2sphere.data.verify import verify_pascal3d

CLASSES = ("aeroplane", "car")


@pytest.fixture(scope="module")
def pascal(tmp_path_factory):
    root = tmp_path_factory.mktemp("pascal")
    records = write_pascal3d(root / "PASCAL3D+_release1.1", classes=CLASSES)
    synthetic = write_renderforcnn(root / "syn", classes=CLASSES)
    return root / "PASCAL3D+_release1.1", records, root / "syn", synthetic


def _by_object(records):
    return {(str(r["image"]), r["object_index"]): r for r in records}


# ------------------------------------------------------------------ rotation conventions


def test_rotation_hand_computed_cases():
    # a = e = t = 0: camera on -y looking at the object's front; object up (z) is image up (y), the
    # object's -y (toward the camera) is +z (toward the viewer)
    np.testing.assert_allclose(pascal3d_rotation(0, 0, 0), [[1, 0, 0], [0, 0, 1], [0, -1, 0]], atol=1e-12)
    # a = 90: camera on +x, so the object's +x points at the viewer and its +y to the right
    np.testing.assert_allclose(pascal3d_rotation(90, 0, 0), [[0, 1, 0], [0, 0, 1], [1, 0, 0]], atol=1e-12)
    # e = 90: looking straight down; object +y is image up, +z toward the viewer
    np.testing.assert_allclose(pascal3d_rotation(0, 90, 0), np.eye(3), atol=1e-12)
    # theta = 90 turns the image by +90 deg: object up (z) now points along -x (left)
    np.testing.assert_allclose(pascal3d_rotation(0, 0, 90) @ [0, 0, 1], [-1, 0, 0], atol=1e-12)
    R = pascal3d_rotation([10.0, 200.0], [-5.0, 30.0], [3.0, -40.0])
    assert R.shape == (2, 3, 3)
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), (2, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    with pytest.raises(ValueError, match="finite"):
        pascal3d_rotation(np.nan, 0, 0)


def test_renderforcnn_tilt_is_negated():
    # a file named ..._a000_e000_t020_... shows the object turned by -20 deg in the image plane
    expected = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]]) @ np.eye(3)
    c, s = math.cos(math.radians(-20)), math.sin(math.radians(-20))
    expected = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]])
    np.testing.assert_allclose(renderforcnn_rotation(0, 0, 20), expected, atol=1e-12)
    np.testing.assert_allclose(renderforcnn_rotation(30, 10, 20), pascal3d_rotation(30, 10, -20), atol=1e-12)
    assert parse_renderforcnn_name("02691156_0a1b_a352_e-05_t-12_d003.png") == ("02691156", 352, -5, -12, 3)
    with pytest.raises(ValueError, match="not a RenderForCNN image name"):
        parse_renderforcnn_name("02691156_0a1b_a352_e005.png")


def test_rotation_reproduces_the_annotation_tool_projection(pascal):
    root, records, _, _ = pascal
    objects, _ = list_pascal3d_objects(root, "train", "all", classes=CLASSES)
    checked = 0
    for obj in objects:
        r = _by_object(records)[(str(obj.image), obj.object_index)]
        C = camera_centre(r["azimuth"], r["elevation"], r["distance"])
        x_cv = GL_TO_CV @ obj.rotation @ (OBJECT_POINTS - C).T  # [3, n]
        pixels = obj.intrinsics() @ x_cv
        pixels = (pixels[:2] / pixels[2]).T + 0.5  # continuous -> 1-based
        expected = project_like_annotation_tool(OBJECT_POINTS, **{k: r[k] for k in (
            "azimuth", "elevation", "theta", "distance", "focal", "viewport", "px", "py")})  # fmt: skip
        np.testing.assert_allclose(pixels, expected, atol=1e-9)
        checked += 1
    assert checked == len(objects) > 10


# ------------------------------------------------------------------ annotations and protocol


def test_annotation_fields_and_protocol_filtering(pascal):
    root, records, _, _ = pascal
    for mode in ("first", "all"):
        for split in ("train", "test"):
            objects, dropped = list_pascal3d_objects(root, split, mode, classes=CLASSES)
            expected = {
                (str(r["image"]), r["object_index"])
                for r in records
                if r["split"] == split and r["kept"] and (r["object_index"] == 0 if mode == "first" else True)
            }
            assert {(str(o.image), o.object_index) for o in objects} == expected
            for o in objects:
                r = _by_object(records)[(str(o.image), o.object_index)]
                assert CLASSES[o.class_index] == r["cls"]
                np.testing.assert_allclose(o.box, r["bbox"])
                assert (o.azimuth, o.theta) == pytest.approx((r["azimuth"], r["theta"]))
    _, dropped = list_pascal3d_objects(root, "train", "first", classes=CLASSES)
    assert {"occluded", "no viewpoint", "distance 0", "degenerate box"} <= set(dropped)
    # a VOC list names images that are not in the release: they are skipped, not reported missing
    voc = (root / "PASCAL/VOCdevkit/VOC2012/ImageSets/Main/car_train.txt").read_text()
    assert "-1" in voc
    objs = read_pascal3d_annotation(next((root / "Annotations" / "car_pascal").glob("*.mat")))
    assert objs[0]["class"] == "car" and len(objs) >= 2


def test_missing_files_and_bad_annotations_are_named(pascal, tmp_path):
    root, _, _, _ = pascal
    with pytest.raises(DatasetNotFoundError, match=r"nowhere.*Images/.*cvgl.stanford.edu.*dataset.root"):
        Pascal3DDataModule(root=str(tmp_path / "nowhere"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetNotFoundError, match=r"missing: Images, Annotations"):
        Pascal3DDataModule(root=str(tmp_path / "empty"))
    with pytest.raises(DatasetNotFoundError, match=r"RenderForCNN.*dataset.synthetic_root"):
        Pascal3DDataModule(root=str(root), synthetic_root=str(tmp_path / "empty"))
    with pytest.raises(ValueError, match="dataset.objects"):
        Pascal3DDataModule(root=str(root), objects="some")
    with pytest.raises(ValueError, match="dataset.augment has unknown keys"):
        Pascal3DDataModule(root=str(root), augment={"flop": True})
    bad = tmp_path / "bad.mat"
    bad.write_bytes(b"MATLAB 5.0 MAT-file, but then nothing")
    with pytest.raises(ValueError, match=r"cannot read PASCAL3D\+ annotation .*bad.mat"):
        read_pascal3d_annotation(bad)


# ------------------------------------------------------------------ warp and augmentation


def _dot_centroids(image: np.ndarray) -> np.ndarray:
    """Continuous pixel centres (x, y) of the three coloured dots ``(3, 2)``."""
    out = []
    for colour in DOT_COLOURS:
        near = np.abs(image.astype(float) - np.array(colour)).sum(-1) < 150
        ys, xs = np.nonzero(near)
        assert len(xs) > 0, f"dot {colour} not visible"
        out.append((xs.mean() + 0.5, ys.mean() + 0.5))
    return np.array(out)


def _dot_residual(image: np.ndarray, R: np.ndarray, points: np.ndarray, C: np.ndarray) -> float:
    """How far (pixels) the dots are from where label ``R`` puts them, for the best focal length of
    a camera centred in the image (the warp's camera)."""
    x = GL_TO_CV @ R @ (points - C).T
    q = (x[:2] / x[2]).T  # [3, 2]
    d = _dot_centroids(image) - image.shape[0] / 2
    f = (q * d).sum() / (q * q).sum()
    return float(np.abs(f * q - d).max())


@pytest.mark.parametrize("split", ["test", "train"])
def test_warped_images_keep_the_dots_where_the_label_puts_them(pascal, split):
    root, records, _, _ = pascal
    objects, _ = list_pascal3d_objects(root, split, "first", classes=CLASSES)
    augment = {"flip": True, "box_jitter": 0.1, "roll_std_deg": 10.0} if split == "train" else None
    ds = Pascal3DDataset(objects, augment=augment, image_size=64, seed=3)
    flips = 0
    for i, obj in enumerate(objects):
        image, R, c = ds.sample(i)
        assert image.shape == (64, 64, 3) and c == obj.class_index
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
        r = _by_object(records)[(str(obj.image), 0)]
        C = camera_centre(r["azimuth"], r["elevation"], r["distance"])
        plain = _dot_residual(image, R, OBJECT_POINTS, C)
        # a flipped image shows the mirrored object: its mirrored points must fit the label instead
        mirrored = _dot_residual(image, R, OBJECT_POINTS @ MIRROR_X, MIRROR_X @ C)
        assert min(plain, mirrored) < 1.0, (i, plain, mirrored)
        assert max(plain, mirrored) > 5.0  # the check can tell the two apart
        flips += mirrored < plain
    if split == "test":
        assert flips == 0
        # no augmentation: the same item every epoch
        ds.set_epoch(5)
        a, b = ds[0], Pascal3DDataset(objects, image_size=64, seed=3)[0]
        torch.testing.assert_close(a["image"], b["image"])
    else:
        assert 0 < flips < len(objects)


def test_warp_maps_box_corners_to_the_output_square():
    K = np.array([[500.0, 0, 300], [0, 500.0, 200], [0, 0, 1]])
    box = np.array([400.0, 50.0, 520.0, 130.0])  # off-centre, wider than tall
    H, W = box_to_virtual_camera(box, K, 100)
    np.testing.assert_allclose(W @ W.T, np.eye(3), atol=1e-12)
    centre = H @ [460.0, 90.0, 1.0]
    np.testing.assert_allclose(centre[:2] / centre[2], [50, 50], atol=1e-9)
    corners = H @ np.array([[400, 50, 1], [520, 50, 1], [400, 130, 1], [520, 130, 1]], float).T
    corners = corners[:2] / corners[2]
    assert np.abs(corners - 50).max() == pytest.approx(50, abs=1e-9)  # fits exactly, centred
    assert (corners >= -1e-9).all() and (corners <= 100 + 1e-9).all()
    with pytest.raises(ValueError, match="x1 < x2"):
        box_to_virtual_camera([5, 5, 5, 9], K, 100)


def test_warp_image_follows_the_homography():
    from PIL import Image

    src = np.zeros((90, 120, 3), np.uint8)
    src[40:44, 70:74] = 255  # a 4x4 block, centre (72, 42)
    K = np.array([[300.0, 0, 60], [0, 300.0, 45], [0, 0, 1]])
    for box, size in (([50, 20, 110, 80], 64), ([0, 0, 120, 90], 20)):  # the second one reduces first
        H, _ = box_to_virtual_camera(np.array(box, float), K, size)
        out = warp_image(Image.fromarray(src), H, size)
        ys, xs = np.nonzero(out[..., 0] > 0)
        weights = out[ys, xs, 0].astype(float)
        found = np.array([(xs * weights).sum(), (ys * weights).sum()]) / weights.sum() + 0.5
        expected = H @ [72.0, 42.0, 1.0]
        np.testing.assert_allclose(found, expected[:2] / expected[2], atol=0.3)


def test_flip_twice_is_the_identity_and_matches_the_angle_rule(pascal):
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
    np.testing.assert_array_equal(hflip_image(hflip_image(image)), image)
    assert not np.array_equal(hflip_image(image), image)
    R = pascal3d_rotation(37.0, 12.0, -8.0)
    np.testing.assert_allclose(hflip_rotation(hflip_rotation(R)), R, atol=1e-12)
    # flipping a PASCAL3D+ view is the view at (-azimuth, elevation, -theta)
    np.testing.assert_allclose(hflip_rotation(R), pascal3d_rotation(-37.0, 12.0, 8.0), atol=1e-12)
    with pytest.raises(ValueError, match=r"got \(2, 2\)"):
        hflip_rotation(np.eye(2))


@pytest.mark.parametrize("shape", ["cube", "cyl"])
def test_flipped_symsol_rendering_is_the_rendering_at_the_flipped_rotation(shape, monkeypatch):
    """For a shape symmetric under x -> -x, the mirrored image is the shape at F R M."""
    from conftest import haar_rotations
    from image2sphere.data import raycast
    from image2sphere.data.raycast import cast_rays, render

    R = haar_rotations(3, seed=11)
    flipped = torch.as_tensor(hflip_rotation(R.numpy()))
    hits, hits_flipped = cast_rays(shape, R, 48), cast_rays(shape, flipped, 48)
    torch.testing.assert_close(hits.hit.flip(-1), hits_flipped.hit)
    torch.testing.assert_close(hits.label.flip(-1), hits_flipped.label)
    mirror = torch.tensor([-1.0, 1.0, 1.0], dtype=hits.normal.dtype)
    torch.testing.assert_close(hits.normal.flip(-2) * mirror, hits_flipped.normal, atol=1e-9, rtol=0)
    torch.testing.assert_close(hits.depth.flip(-1), hits_flipped.depth, equal_nan=True, atol=1e-9, rtol=0)
    # the shaded image too, once the light itself is left-right symmetric (the default light comes
    # from the upper left, so its mirror image is lit from the upper right)
    n = math.sqrt(0.5**2 + 1)
    monkeypatch.setattr(raycast, "LIGHT_DIRECTION", (0.0, 0.5 / n, 1.0 / n))
    images = render(shape, R, image_size=48).numpy()
    images_flipped = render(shape, flipped, image_size=48).numpy()
    diff = np.abs(hflip_image(images).astype(int) - images_flipped.astype(int))
    assert diff.max() <= 1  # float rounding of the shading only
    assert np.abs(images.astype(int) - images_flipped.astype(int)).max() > 50  # the flip does change the image


# ------------------------------------------------------------------ synthetic mixing and the data module


def test_renderforcnn_listing_and_mixing(pascal):
    root, _, syn_root, synthetic = pascal
    views, bad = list_renderforcnn(syn_root, CLASSES)
    assert len(views) == len(synthetic) and not bad
    truth = {str(r["path"]): r for r in synthetic}
    for v in views:
        r = truth[str(v.path)]
        assert (CLASSES[v.class_index], v.tilt) == (r["cls"], r["tilt"])
        np.testing.assert_allclose(v.rotation, pascal3d_rotation(r["azimuth"], r["elevation"], -r["tilt"]))
    objects, _ = list_pascal3d_objects(root, "train", "first", classes=CLASSES)
    ds = Pascal3DDataset(objects, views, synthetic_ratio=3, augment={}, image_size=32, seed=0)
    assert len(ds) == 4 * len(objects)
    draws = [ds.source(i) for i in range(len(objects), len(ds))]
    assert all(d in views for d in draws)
    assert [ds.source(i) for i in range(len(objects), len(ds))] == draws  # a function of (seed, epoch, i)
    ds.set_epoch(1)
    assert [ds.source(i) for i in range(len(objects), len(ds))] != draws
    item = ds[len(objects)]
    assert item["image"].shape == (3, 32, 32) and item["rotation"].shape == (3, 3)
    assert len(Pascal3DDataset(objects, views, synthetic_ratio=0.5)) == len(objects) + round(0.5 * len(objects))
    assert len(Pascal3DDataset(objects, None, synthetic_ratio=3)) == len(objects)


def test_data_module_splits_loaders_and_corrupt_images(pascal, tmp_path):
    import shutil

    root, _, syn_root, _ = pascal
    dm = Pascal3DDataModule(
        root=str(root), synthetic_root=str(syn_root), image_size=32, batch_size=4, val_per_class=1, seed=0,
        classes=CLASSES,
    )  # fmt: skip
    dm.setup("fit")
    dm.setup("test")
    n_train = len(dm.data_train.real)
    assert len(dm.data_train) == 4 * n_train
    val_images = {o.image for o in dm.data_val.real}
    assert val_images and not val_images & {o.image for o in dm.data_train.real}
    batch = next(iter(dm.train_dataloader()))
    assert batch["image"].shape == (4, 3, 32, 32) and batch["rotation"].shape == (4, 3, 3)
    assert int(batch["skipped"]) == 0
    test_batch = next(iter(dm.test_dataloader()))
    assert test_batch["rotations"].shape[1:] == (1, 3, 3) and test_batch["mask"].all()
    assert dm.class_names == list(CLASSES)

    # a truncated image: named on "fail", skipped and counted on "skip"
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    objects, _ = list_pascal3d_objects(copy, "test", "first", classes=CLASSES)
    data = objects[0].image.read_bytes()
    objects[0].image.write_bytes(data[: len(data) // 2])
    with pytest.raises(CorruptImageError, match=objects[0].image.name):
        Pascal3DDataset(objects, return_all=True)[0]
    ds = Pascal3DDataset(objects, return_all=True, on_corrupt="skip", image_size=32)
    batch = collate_skipping_corrupt([ds[i] for i in range(len(ds))])
    assert int(batch["skipped"]) == 1 and len(batch["image"]) == len(objects) - 1
    report = verify_pascal3d(copy, syn_root, progress=False, classes=CLASSES)
    assert not report.ok and report.unreadable == [str(objects[0].image)]


def test_verify_counts_and_missing_listed_images(pascal, tmp_path):
    import shutil

    root, records, syn_root, synthetic = pascal
    report = verify_pascal3d(root, syn_root, decode_synthetic=True, progress=False, classes=CLASSES)
    assert report.ok, report.format()
    counts = {(s, c): (found, exp) for s, c, found, exp in report.counts}
    kept_test = sum(
        r["kept"] and r["split"] == "test" and r["cls"] == "car" and r["object_index"] == 0 for r in records
    )
    assert counts[("test objects kept", "car")] == (kept_test, None)
    assert counts[("synthetic images", "car")] == (sum(r["cls"] == "car" for r in synthetic), None)
    assert counts[("train imagenet images", "aeroplane")] == (6, 6)
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    gone = next((copy / "Images" / "car_imagenet").glob("*.JPEG"))
    gone.unlink()
    report = verify_pascal3d(copy, progress=False, classes=CLASSES)
    assert not report.ok
    assert any(str(gone) in p for p in report.problems)
    assert ("train imagenet images", "car", 5, 6) in report.counts
    assert "mismatch" in report.format()
