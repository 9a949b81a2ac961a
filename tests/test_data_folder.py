"""``dataset=folder``: a user's folder of images and one labels file (:mod:`image2sphere.data.folder`).

The built-in renderer's images and rotations are written out as a user would (PNGs and a CSV, once as an NPZ
with every image's equivalent rotations) and read back: the items equal the built-in dataset's, and a run
trains and tests to the same metrics. Every bad input is refused in one line naming the file and row, and
leaves no run directory. Quick tier, except the two trainings (slow).
"""

from __future__ import annotations

import csv
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import TINY, read_metrics, run_module
from image2sphere.data.datamodule import FolderDataModule, SymsolDataModule
from image2sphere.so3.rotations import matrix_to_quaternion

SHAPE_RENDER = {"train": 10, "test": 3, "image_size": 32}


@pytest.fixture(scope="module")
def symsol(tmp_path_factory):
    """The renderer's cube and tetX (one marked face: one to nine equivalent rotations per image), as the
    built-in data module reads them (2 validation images per shape carved from the training split)."""
    out = {}
    for shape in ("cube", "tetX"):
        dm = SymsolDataModule(shapes=[shape], render={**SHAPE_RENDER, "shapes": [shape]},
                              render_dir=str(tmp_path_factory.mktemp("render")), image_size=32, val_per_shape=2,
                              label="first", batch_size=4)  # fmt: skip
        dm.prepare_data()
        dm.setup()
        out[shape] = dm
    return out


def _export(dm: SymsolDataModule, folder: Path, kind: str = "csv", order: str = "wxyz") -> Path:
    """The data module's images copied into ``folder/images`` and their labels written as a user would:
    train, then val, then test rows (each in the data module's order) with a split and a class column."""
    (folder / "images").mkdir(parents=True)
    rows = []
    for split, data in (("train", dm.data_train), ("val", dm.data_val), ("test", dm.data_test)):
        for i in range(len(data)):
            c, r = data.items[i]
            name = f"{split}_{i:03d}.png"
            shutil.copy(data.image_path(i), folder / "images" / name)
            sets, count = data.rotations[c][r], int(data.counts[c][r])
            rows.append((f"images/{name}", sets[:count], dm.shapes[c], split))
    if kind == "csv":
        columns = ["qw", "qx", "qy", "qz"] if order == "wxyz" else ["qx", "qy", "qz", "qw"]
        with open(folder / "labels.csv", "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["image", *columns, "class", "split"])
            for path, sets, cls, split in rows:
                q = matrix_to_quaternion(sets[0].double(), order).tolist()
                writer.writerow([path, *(repr(v) for v in q), cls, split])
        return folder / "labels.csv"
    m = max(len(s) for _, s, _, _ in rows)
    equivalent = np.full((len(rows), m, 3, 3), np.nan)
    for i, (_, sets, _, _) in enumerate(rows):
        equivalent[i, : len(sets)] = sets.double().numpy()
    arrays = {"image": np.array([r[0] for r in rows]), "rotation": equivalent[:, 0], "equivalent": equivalent,
              "class": np.array([r[2] for r in rows]), "split": np.array([r[3] for r in rows])}  # fmt: skip
    np.savez(folder / "labels.npz", **arrays)
    return folder / "labels.npz"


def _same_items(ours, theirs) -> None:
    assert len(ours) == len(theirs)
    for i in range(len(ours)):
        a, b = ours[i], theirs[i]
        torch.testing.assert_close(a["image"], b["image"], rtol=0, atol=0)
        assert int(a["class_index"]) == int(b["class_index"])
        assert ("rotation" in a) == ("rotation" in b) and ("mask" in a) == ("mask" in b)
        if "rotation" in a:
            torch.testing.assert_close(a["rotation"], b["rotation"], rtol=0, atol=2e-6)
        else:  # the same set (its padding may be longer in one: the largest set of its split or of its file)
            torch.testing.assert_close(a["rotations"][a["mask"]], b["rotations"][b["mask"]], rtol=0, atol=2e-6)


@pytest.mark.parametrize("order", ["wxyz", "xyzw"])
def test_a_csv_of_the_renderers_cube_reads_as_the_built_in_dataset_with_its_symmetry_group(symsol, tmp_path, order):
    """Quick. The cube's images and one rotation each in a CSV (quaternions in either order the header names),
    with ``symmetry=O``: every split's items equal the built-in module's, the 24 equivalent rotations of each
    test image included (the cube's SYMSOL set is ``R @ S`` over scipy's octahedral group)."""
    dm = symsol["cube"]
    _export(dm, tmp_path / "mine", order=order)
    folder = FolderDataModule(str(tmp_path / "mine"), symmetry="O", image_size=32, label="first", batch_size=4)
    folder.setup()
    assert folder.class_names == ["cube"]
    for split in ("data_train", "data_val", "data_test"):
        _same_items(getattr(folder, split), getattr(dm, split))


def test_an_npz_with_each_images_equivalent_rotations_reads_as_the_built_in_tetx(symsol, tmp_path):
    """Quick. tetX (a marked face: sets of 1 to 9 rotations) written as an NPZ with NaN-padded sets."""
    dm = symsol["tetX"]
    _export(dm, tmp_path / "mine", kind="npz")
    folder = FolderDataModule(str(tmp_path / "mine"), labels="labels.npz", image_size=32, label="first", batch_size=4)
    folder.setup()
    counts = [int(folder.data_test[i]["mask"].sum()) for i in range(len(folder.data_test))]
    assert len(set(counts)) > 1 or counts == [1] * len(counts)  # sets of their own sizes, as read
    for split in ("data_train", "data_val", "data_test"):
        _same_items(getattr(folder, split), getattr(dm, split))


def test_without_a_split_column_the_fractions_draw_a_seeded_split(symsol, tmp_path):
    dm = symsol["cube"]
    labels = _export(dm, tmp_path / "mine")
    text = labels.read_text().splitlines()
    labels.write_text("\n".join(",".join(line.split(",")[:-1]) for line in text) + "\n")  # no split column
    a, b, c = (FolderDataModule(str(tmp_path / "mine"), val_fraction=0.2, test_fraction=0.2, seed=s)
               for s in (0, 0, 1))  # fmt: skip
    n = len(text) - 1
    assert [len(a.splits[s]) for s in ("train", "val", "test")] == [n - 2 * round(0.2 * n), round(0.2 * n),
                                                                     round(0.2 * n)]  # fmt: skip
    assert sorted(np.concatenate(list(a.splits.values())).tolist()) == list(range(n))
    assert all(np.array_equal(a.splits[s], b.splits[s]) for s in a.splits)
    assert not all(np.array_equal(a.splits[s], c.splits[s]) for s in a.splits)


def _train(overrides: list[str], data_dir: Path, log_dir: Path, run: Path, check: bool = True):
    tiny = [o for o in TINY if not o.startswith(("dataset.render", "dataset.val_per_shape"))]
    argv = [sys.executable, "-m", "src.train", *tiny, f"paths.data_dir={data_dir}", f"paths.log_dir={log_dir}",
            "logger=none", "trainer.max_epochs=2", "dataset.batch_size=4", "dataset.num_workers=0",
            f"hydra.run.dir={run}", *overrides]  # fmt: skip
    return run_module(argv, check=check)


@pytest.mark.slow
def test_a_run_on_the_exported_folder_trains_and_tests_as_on_the_built_in_data(symsol, tmp_path):
    """Slow. The same two epochs (seed 0, the built-in data's protocol, the first label of each image, the same
    batches) on the rendered cube read as SYMSOL and on its export as a folder with ``symmetry=O``: the same
    test metrics."""
    dm = symsol["cube"]
    _export(dm, tmp_path / "mine")
    common = ["dataset.label=first", "seed=0", "protocol=symsol_rendered"]
    _train([*common, "dataset=symsol1", f"dataset.root={dm.root}", "dataset.shapes=[cube]", "dataset.val_per_shape=2"],
           tmp_path / "data", tmp_path / "logs", tmp_path / "builtin")  # fmt: skip
    _train([*common, "dataset=folder", f"dataset.root={tmp_path / 'mine'}", "dataset.symmetry=O"],
           tmp_path / "data", tmp_path / "logs", tmp_path / "folder")  # fmt: skip
    builtin, folder = read_metrics(tmp_path / "builtin"), read_metrics(tmp_path / "folder")
    assert folder["n_images"] == builtin["n_images"] == SHAPE_RENDER["test"]
    for key in ("log_likelihood", "median_error_deg", "acc15", "spread_deg"):
        assert folder[key] == pytest.approx(builtin[key], rel=1e-5, abs=1e-6), key


# ------------------------------------------------------------------------------------------ bad input
def _csv(folder: Path, header: str, *rows: str) -> None:
    (folder / "images").mkdir(parents=True, exist_ok=True)
    from PIL import Image

    Image.new("RGB", (8, 8), (120, 30, 200)).save(folder / "images" / "a.png")
    (folder / "labels.csv").write_text("\n".join([header, *rows]) + "\n")


GOOD = "images/a.png,1,0,0,0"
BAD_INPUTS = {
    "no rotation columns": ("image,a,b", ["images/a.png,1,2"], "the header must name one rotation"),
    "a field missing": ("image,qw,qx,qy,qz", [GOOD, "images/a.png,1,0,0"], "labels.csv, row 3: 4 fields"),
    "a quaternion far from unit": ("image,qw,qx,qy,qz", [GOOD, "images/a.png,2,0,0,0"],
                                   "labels.csv, row 3: the quaternion has norm 2"),
    "a reflection": ("image," + ",".join(f"r{i}{j}" for i in range(3) for j in range(3)),
                     ["images/a.png,1,0,0,0,1,0,0,0,-1"], "labels.csv, row 2: the matrix has determinant -1"),
    "not orthonormal": ("image," + ",".join(f"r{i}{j}" for i in range(3) for j in range(3)),
                        ["images/a.png,1,0.5,0,0,1,0,0,0,1"], "labels.csv, row 2: the matrix is not a rotation"),
    "a missing image": ("image,qw,qx,qy,qz,split", [GOOD + ",train", "images/gone.png,1,0,0,0,test"],
                        "labels.csv, row 3: the image"),
    "an unknown split": ("image,qw,qx,qy,qz,split", ["images/a.png,1,0,0,0,train", "images/a.png,1,0,0,0,tset"],
                         "labels.csv, row 3: split 'tset'"),
    "an empty test split": ("image,qw,qx,qy,qz,split", ["images/a.png,1,0,0,0,train"], "no test images"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_each_bad_input_is_one_line_naming_the_file_and_row_and_leaves_no_run_directory(case, tmp_path):
    header, rows, message = BAD_INPUTS[case]
    _csv(tmp_path / "mine", header, *rows)
    run = tmp_path / "run"
    proc = _train(["dataset=folder", f"dataset.root={tmp_path / 'mine'}"], tmp_path / "data", tmp_path / "logs",
                  run, check=False)  # fmt: skip
    lines = [line for line in proc.stderr.strip().splitlines() if line != "Seed set to 0"]  # the run's own log
    assert proc.returncode == 1 and len(lines) == 1 and lines[0].startswith("Error: "), proc.stderr[-2000:]
    assert message in lines[0], lines[0]
    assert not run.exists()


def test_a_corrupt_image_an_unknown_group_and_near_unit_quaternions(tmp_path, caplog):
    """Quick. An image whose header does not read, named with its row; a group name that is none; a
    quaternion 0.5 % off unit norm normalised with a note, not refused."""
    from image2sphere.checks import ConfigError

    _csv(tmp_path / "mine", "image,qw,qx,qy,qz,split", "images/a.png,1,0,0,0,train", "images/b.png,1,0,0,0,test")
    (tmp_path / "mine" / "images" / "b.png").write_bytes(b"not a png")
    with pytest.raises(ConfigError, match=r"labels.csv, row 3: the image .*b.png cannot be read"):
        FolderDataModule(str(tmp_path / "mine"))
    _csv(tmp_path / "ok", "image,qw,qx,qy,qz,split", "images/a.png,1.005,0,0,0,train", "images/a.png,1,0,0,0,test")
    with caplog.at_level("INFO"):
        dm = FolderDataModule(str(tmp_path / "ok"))
    assert "1 of 2 rotations were not exactly unit" in caplog.text
    torch.testing.assert_close(torch.from_numpy(dm.table.rotations[0]), torch.eye(3))
    with pytest.raises(ConfigError, match=r"dataset.symmetry: 'X7' \(for 'ok'\) is not a group"):
        FolderDataModule(str(tmp_path / "ok"), symmetry="X7")


# ------------------------------------------------------------------------------------------ the convention check
def test_label_axes_follow_the_camera_frame_and_the_check_draws_once(tmp_path):
    """Quick. ``axes_in_image``: under the identity the object's x axis points right, y up (toward row 0), z at
    the viewer; a quarter turn about z takes x to where y was. On the fixture folder, whose discs are drawn
    where each label's z axis points, the disc's centre is where the drawn z axis points. The command writes
    its picture once and refuses to overwrite it, in one line."""
    from PIL import Image

    from image2sphere.data.fixtures.folder import write_folder
    from image2sphere.data.folder import axes_in_image, main, read_labels

    identity = axes_in_image(np.eye(3), 100)
    np.testing.assert_allclose(identity, [[40, 0, 0], [0, -40, 0], [0, 0, 1]], atol=1e-12)
    quarter = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # x_camera = R @ x_object: object x -> camera y
    np.testing.assert_allclose(axes_in_image(quarter, 100)[0], [0, -40, 0], atol=1e-12)
    root = write_folder(tmp_path / "my_poses", per_class=4, image_size=64)
    table = read_labels(root / "labels.csv")
    for path, R in zip(table.paths, table.rotations, strict=True):
        pixels = np.asarray(Image.open(root / path).convert("L"), dtype=np.float64)
        rows, cols = np.nonzero(pixels > 40)  # the disc (the background is 20)
        dx, dy, _ = axes_in_image(R, 64)[2]
        inside = (cols.mean() - 32, rows.mean() - 32)
        if abs(dx) < 20 and abs(dy) < 20:  # a disc cut by the border has its centroid pulled inwards
            np.testing.assert_allclose(inside, (dx / 0.8, dy / 0.8), atol=1.5, err_msg=path)
    out = tmp_path / "axes.png"
    assert main([str(root), "--out", str(out)]) == 0 and out.read_bytes()[:4] == b"\x89PNG"
    before = out.read_bytes()
    assert main([str(root), "--out", str(out)]) == 1 and out.read_bytes() == before
