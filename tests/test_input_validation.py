"""Bad input to prediction (``predict``, ``Predictor``, image decoding) and to the public SO(3) API is
refused with a clear error, or handled by a documented rule, before any expensive work starts.

The checkpoint used here is an untrained tiny I2S built directly from a model config (no training):
only the plumbing around the network is under test.
"""

from __future__ import annotations

import io
import logging
import math
import re
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from matplotlib.figure import Figure
from PIL import Image

from image2sphere.checks import check_int, check_number
from image2sphere.data import common
from image2sphere.data.common import decode_image, image_to_uint8, load_image
from image2sphere.distributions import SO3Distribution
from image2sphere.inference import Predictor, predict
from image2sphere.plot import figure_format, save_figure
from image2sphere.so3 import (
    MAX_DENSE_LEVEL,
    MAX_STREAMED_LEVEL,
    HealpixGridEvaluator,
    check_level,
    dense_grid_logits,
    flat_wigner,
    flat_wigner_from_angles,
    geodesic_distance_deg,
    get_grid_evaluator,
    left_translate_so3_coeffs,
    n_s2_coeffs,
    n_so3_coeffs,
    rotate_s2_coeffs,
    so3_blocks,
    so3_grid_size,
    so3_healpix_grid,
    so3_healpix_grid_angles,
    so3_healpix_index_to_matrix,
    so3_healpix_nearest_index,
    so3_layout,
    so3_near_identity_grid,
    wigner_D,
)
from image2sphere.so3.grid_eval import check_streamed_level

LMAX = 2
N_COEFFS = n_so3_coeffs(LMAX)  # 35


# ---------------------------------------------------------------------------------- fixtures
def _model_config(num_classes: int = 0) -> dict:
    encoder = {"_target_": "image2sphere.nn.ResNetEncoder", "depth": 18, "weights": None}
    net = {"_target_": "image2sphere.nn.I2S", "encoder": encoder, "image_size": 32, "lmax": LMAX,
           "sphere_channels": 8, "so3_channels": 4, "activation_resolution": 4, "num_classes": num_classes}  # fmt: skip
    return {
        "_target_": "image2sphere.training.PoseEstimationModule",
        "net": net,
        "optimizer": {"_target_": "torch.optim.SGD", "_partial_": True, "lr": 1e-3},
        "train_grid_level": 2,
        "val_grid_level": 2,
        "eval_grid_level": 3,
        "spread_grid_level": 2,
    }


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    """A checkpoint of an untrained model without class input, in the layout ``python -m src.train``
    writes (state dict plus what the module adds in ``on_save_checkpoint``)."""
    torch.manual_seed(0)
    run_config = {"model": _model_config(), "dataset": {"image_size": 32}}
    module = instantiate(run_config["model"])
    module.run_config = run_config
    module.class_names = ["cube"]
    content = {"state_dict": module.state_dict()}
    module.on_save_checkpoint(content)
    path = tmp_path_factory.mktemp("ckpt") / "last.ckpt"
    torch.save(content, path)
    return path


@pytest.fixture
def photo(tmp_path) -> Path:
    path = tmp_path / "photo.png"
    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 256, (40, 40, 3), dtype=np.uint8)).save(path)
    return path


class FakeNet(torch.nn.Module):
    """Zero coefficients of band limit 1; remembers the class indices it was called with."""

    lmax = 1

    def __init__(self, num_classes: int):
        super().__init__()
        self.num_classes = num_classes
        self.seen = "not called"

    def forward(self, images, class_index=None):
        self.seen = class_index
        return torch.zeros(len(images), n_so3_coeffs(self.lmax))


def _png_bytes(image: Image.Image) -> bytes:
    buffer = io.BytesIO()
    image.save(buffer, "PNG")
    return buffer.getvalue()


# ---------------------------------------------------------------------------------- image decoding
def test_16_bit_grayscale_decodes_like_its_8_bit_version(tmp_path):
    rng = np.random.default_rng(1)
    gray8 = np.tile(np.arange(256, dtype=np.uint8), (8, 1))  # a full gradient
    # the 16-bit version of every 8-bit level, with sub-level detail that must round away
    gray16 = (gray8.astype(np.int64) * 257 + rng.integers(-128, 129, gray8.shape)).clip(0, 65535).astype(np.uint16)
    Image.fromarray(gray8).save(tmp_path / "gray8.png")
    Image.fromarray(gray16).save(tmp_path / "gray16.png")
    assert Image.open(tmp_path / "gray16.png").mode.startswith("I")  # really a 16-bit file
    eight, sixteen = load_image(tmp_path / "gray8.png"), load_image(tmp_path / "gray16.png")
    assert sixteen.shape == eight.shape == (8, 256, 3) and sixteen.dtype == torch.uint8
    assert (sixteen.int() - eight.int()).abs().max() <= 1
    assert torch.equal(sixteen[..., 0], sixteen[..., 1]) and torch.equal(sixteen[..., 0], sixteen[..., 2])
    # the same rule for images handed over in memory: 32-bit integer ("I") and float ("F") modes
    as_int = Image.fromarray(gray16.astype(np.int32))
    as_float = Image.fromarray(gray8.astype(np.float32) / 255)
    assert (as_int.mode, as_float.mode) == ("I", "F")
    for image in (Image.open(tmp_path / "gray16.png"), as_int, as_float):
        assert (image_to_uint8(image).int() - eight.int()).abs().max() <= 1, image.mode


def test_high_bit_depth_values_that_fit_no_rule_are_refused_naming_the_image(tmp_path):
    Image.fromarray(np.full((4, 4), 2.5, np.float32)).save(tmp_path / "bright.tiff")
    with pytest.raises(ValueError, match=r"bright.tiff is a float image with values in \[2.5, 2.5\].*\[0, 1\]"):
        decode_image(tmp_path / "bright.tiff")
    with pytest.raises(ValueError, match=r"32-bit integer image .*\(0\.\.65535\)"):
        image_to_uint8(Image.fromarray(np.full((4, 4), 70000, np.int32)))


def test_transparent_pixels_are_composited_onto_black_and_reported_once(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(common, "_transparency_reported", False, raising=False)
    rgba = np.zeros((3, 4, 4), np.uint8)
    rgba[..., :3] = (200, 50, 30)  # whatever colour happens to be stored under the alpha
    rgba[0, :, 3] = 0  # fully transparent row
    rgba[1, :, 3] = 255  # opaque row
    rgba[2, :, 3] = 128  # half transparent row
    with caplog.at_level(logging.WARNING, logger="image2sphere.data.common"):
        out = load_image(_png_bytes(Image.fromarray(rgba)), name="rgba.png").numpy()
        la = Image.fromarray(np.ascontiguousarray(rgba[..., [0, 3]]))
        assert la.mode == "LA"
        out_la = load_image(_png_bytes(la), name="la.png").numpy()
    assert (out[0] == 0).all()  # the background colour, not (200, 50, 30)
    assert (out[1] == (200, 50, 30)).all()
    assert (out[2] == np.round(np.array([200, 50, 30]) * 128 / 255)).all()
    assert (out_la[0] == 0).all() and (out_la[1] == 200).all() and (out_la[2] == round(200 * 128 / 255)).all()
    warnings = [r for r in caplog.records if "transparent" in r.getMessage()]
    assert len(warnings) == 1 and "rgba.png" in warnings[0].getMessage() and "black" in warnings[0].getMessage()
    # a palette image with a transparent colour, from a file and as a PIL image
    palette = Image.new("P", (2, 2))
    palette.putdata([0, 1, 1, 0])
    palette.putpalette([250, 250, 250, 10, 20, 30] + [0] * 762)
    palette.info["transparency"] = 0
    palette.save(tmp_path / "palette.png", transparency=0)
    expected = np.array([[[0, 0, 0], [10, 20, 30]], [[10, 20, 30], [0, 0, 0]]])
    assert (np.asarray(decode_image(tmp_path / "palette.png")) == expected).all()
    assert (image_to_uint8(palette).numpy() == expected).all()
    keyed = Image.fromarray(np.array([[[200, 50, 30], [1, 2, 3]]], np.uint8))  # RGB with a transparent colour
    keyed.info["transparency"] = (200, 50, 30)
    assert image_to_uint8(keyed).tolist() == [[[0, 0, 0], [1, 2, 3]]]
    # opaque RGBA is not "transparency": unchanged, and no warning
    caplog.clear()
    monkeypatch.setattr(common, "_transparency_reported", False)
    opaque = rgba.copy()
    opaque[..., 3] = 255
    with caplog.at_level(logging.WARNING, logger="image2sphere.data.common"):
        assert (load_image(_png_bytes(Image.fromarray(opaque))).numpy() == (200, 50, 30)).all()
    assert not caplog.records


def test_predictor_applies_the_same_rules_to_pil_images():
    predictor = Predictor(FakeNet(0), image_size=4)
    rgba = np.zeros((4, 4, 4), np.uint8)
    rgba[..., :3] = 255  # white under zero alpha
    x = predictor.preprocess(Image.fromarray(rgba))
    black = predictor.preprocess(Image.fromarray(np.zeros((4, 4, 3), np.uint8)))
    torch.testing.assert_close(x, black)


# ---------------------------------------------------------------------------------- thresholds
@pytest.mark.parametrize("bad", [0.0, -0.1, 1.5, 2.0, math.nan, math.inf, True])
def test_threshold_outside_zero_one_is_refused_naming_it(bad):
    dist = SO3Distribution(torch.zeros(1, N_COEFFS), LMAX)
    with pytest.raises(ValueError, match=r"threshold must be > 0 and <= 1 \(a probability in \(0, 1\]\)"):
        dist.modes(level=1, threshold=bad)
    with pytest.raises(ValueError, match=r"threshold must be"):
        dist.points_above(bad, level=1)


def test_a_threshold_no_point_reaches_gives_no_modes():
    torch.manual_seed(0)
    dist = SO3Distribution(0.1 * torch.randn(2, N_COEFFS, dtype=torch.float64), LMAX)
    top = dist.log_prob_grid(2).exp().amax(dim=1)
    assert (top < 0.5).all()
    for rotations, mass in dist.modes(level=2, threshold=0.5):
        assert rotations.shape == (0, 3, 3) and mass.shape == (0,)
    for rotations, mass in dist.modes(level=2, threshold=0.5, refine=True):
        assert rotations.shape == (0, 3, 3) and mass.shape == (0,)
    # a threshold just below the top probability keeps exactly the top point
    (rotations, mass), _ = dist.modes(level=2, threshold=float(top[0]) * (1 - 1e-9))
    assert rotations.shape == (1, 3, 3) and mass.shape == (1,)
    torch.testing.assert_close(dist.max_prob(2), top)  # what to compare an unreachable threshold with


def test_predict_with_an_unreachable_threshold_says_so(checkpoint, photo, capsys):
    out = predict(str(checkpoint), str(photo), level=2, threshold=0.5)
    printed = capsys.readouterr().out
    assert "no modes: no grid point reaches threshold=0.5 at level 2" in printed and "lower the threshold" in printed
    assert out["rotations"].shape == (0, 3, 3) and out["mass"].shape == (0,)
    assert out["plot"].read_bytes()[:4] == b"\x89PNG"


def test_predict_checks_its_arguments_before_loading_anything(photo, tmp_path):
    missing = str(tmp_path / "no.ckpt")  # reaching the checkpoint would raise CheckpointError instead
    with pytest.raises(ValueError, match=r"threshold must be > 0 and <= 1"):
        predict(missing, str(photo), threshold=2.0)
    with pytest.raises(ValueError, match=r"level=8 is too fine"):
        predict(missing, str(photo), level=8)
    with pytest.raises(ValueError, match=r"top_k must be an integer >= 1, got 0"):
        predict(missing, str(photo), top_k=0)
    with pytest.raises(ValueError, match=r"output=.*x.foo has extension .foo: a plot is written as one of .png, .jpg"):
        predict(missing, str(photo), output=str(tmp_path / "x.foo"))
    with pytest.raises(ValueError, match=r"has no extension"):
        predict(missing, str(photo), output=str(tmp_path / "plot"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photo.png"]  # nothing written


# ---------------------------------------------------------------------------------- plot files
def test_predict_writes_the_format_the_extension_names_and_never_overwrites_a_file(checkpoint, photo, tmp_path, capsys):
    out = predict(str(checkpoint), str(photo), level=2, output=str(tmp_path / "x.jpg"))
    assert out["plot"] == tmp_path / "x.jpg" and (tmp_path / "x.jpg").read_bytes()[:2] == b"\xff\xd8"
    assert "mode 1: mass" in capsys.readouterr().out
    default = predict(str(checkpoint), str(photo), level=2)["plot"]
    assert default == tmp_path / "photo_so3.png" and default.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # an existing file of either kind is never overwritten, nor a reason to stop: the plot gets the next free
    # name, which the printed line gives, and the modes are printed again
    capsys.readouterr()
    (tmp_path / "keep.jpg").write_bytes(b"mine")
    (tmp_path / "keep-1.jpg").write_bytes(b"mine too")
    out = predict(str(checkpoint), str(photo), level=2, output=str(tmp_path / "keep.jpg"))
    assert out["plot"] == tmp_path / "keep-2.jpg" and out["plot"].read_bytes()[:2] == b"\xff\xd8"
    printed = capsys.readouterr().out
    assert "mode 1: mass" in printed and f"plot: {tmp_path / 'keep-2.jpg'} ({tmp_path / 'keep.jpg'} exists" in printed
    assert (tmp_path / "keep.jpg").read_bytes() == b"mine" and (tmp_path / "keep-1.jpg").read_bytes() == b"mine too"


def test_save_figure_follows_the_extension(tmp_path):
    fig = Figure(figsize=(1, 1))
    fig.add_subplot().plot([0, 1])
    magic = {"a.png": b"\x89PNG", "b.jpg": b"\xff\xd8", "c.JPEG": b"\xff\xd8", "d.pdf": b"%PDF", "e.svg": b"<?xml"}
    for name, start in magic.items():
        assert save_figure(fig, tmp_path / name).read_bytes().startswith(start), name
    with pytest.raises(ValueError, match=r"extension .foo"):
        save_figure(fig, tmp_path / "f.foo")
    assert not (tmp_path / "f.foo").exists()
    before = (tmp_path / "b.jpg").read_bytes()
    from image2sphere.checks import OutputExistsError

    with pytest.raises(OutputExistsError, match=r"b.jpg already exists and is not overwritten"):  # a refusal
        save_figure(fig, tmp_path / "b.jpg")
    assert (tmp_path / "b.jpg").read_bytes() == before
    assert figure_format("x.Tif") == "tif"


# ---------------------------------------------------------------------------------- class input
def test_class_index_for_a_model_without_class_input_is_refused(checkpoint, photo):
    net = FakeNet(0)
    predictor = Predictor(net, image_size=8)
    with pytest.raises(ValueError, match=r"trained without class input: leave class_index out \(null\), got 1"):
        predictor(np.zeros((8, 8, 3), np.uint8), class_index=1)
    assert net.seen == "not called"
    assert predictor(np.zeros((8, 8, 3), np.uint8)).batch_size == 1
    with pytest.raises(ValueError, match=r"trained without class input"):
        predict(str(checkpoint), str(photo), class_index=0, level=2)
    assert not (photo.parent / "photo_so3.png").exists()


def test_class_index_of_a_class_model_is_checked():
    net = FakeNet(3)
    predictor = Predictor(net, image_size=8, class_names=["a", "b", "c"])
    images = [np.zeros((8, 8, 3), np.uint8)] * 2
    with pytest.raises(ValueError, match=r"pass class_index \(0=a, 1=b, 2=c\)"):
        predictor(images)
    for bad in (3, -1, [0, 5]):
        with pytest.raises(ValueError, match=r"out of range: this model knows the classes 0..2 \(0=a, 1=b, 2=c\)"):
            predictor(images, class_index=bad)
    for bad in (1.5, True, "b"):
        with pytest.raises(ValueError, match=r"class_index must be an integer in \[0, 3\)"):
            predictor(images, class_index=bad)
    with pytest.raises(ValueError, match=r"one integer or one per image \(2\), got 3"):
        predictor(images, class_index=[0, 1, 2])
    assert net.seen == "not called"
    predictor(images, class_index=2)
    assert net.seen.tolist() == [2, 2]
    predictor(images, class_index=[0, 1])
    assert net.seen.tolist() == [0, 1]


# ---------------------------------------------------------------------------------- SO3Distribution
def test_non_finite_coefficients_are_refused_naming_the_batch_entries():
    coeffs = torch.zeros(4, N_COEFFS)
    coeffs[1, 3] = math.nan
    coeffs[3, 0] = -math.inf
    with pytest.raises(ValueError, match=r"NaN or infinite values in 2 of 4 distributions \(batch entries 1, 3\)"):
        SO3Distribution(coeffs, LMAX)
    SO3Distribution(coeffs.nan_to_num(0.0, 0.0, 0.0), LMAX)  # finite: fine


def test_refinement_parameters_are_checked():
    torch.manual_seed(0)
    dist = SO3Distribution(torch.randn(2, N_COEFFS, dtype=torch.float64), LMAX)
    # steps=0: no refinement, the grid argmax
    torch.testing.assert_close(dist.mode(1, refine=True, steps=0), dist.mode(1), rtol=0, atol=0)
    for steps in (-1, 2.5, True, None):
        with pytest.raises(ValueError, match=r"steps must be an integer >= 0"):
            dist.mode(1, refine=True, steps=steps)
    for lr in (0.0, -0.1, math.nan, math.inf, "0.1"):
        with pytest.raises(ValueError, match=r"lr must be a finite number > 0"):
            dist.mode(1, refine=True, steps=3, lr=lr)


# ---------------------------------------------------------------------------------- lmax and l
_R = torch.eye(3, dtype=torch.float64)[None]
_ANGLES = (torch.zeros(1, dtype=torch.float64),) * 3
LMAX_FUNCTIONS = {
    "wigner_D": lambda l: wigner_D(l, *_ANGLES),
    "flat_wigner": lambda l: flat_wigner(l, _R),
    "flat_wigner_from_angles": lambda l: flat_wigner_from_angles(l, *_ANGLES),
    "n_so3_coeffs": n_so3_coeffs,
    "n_s2_coeffs": n_s2_coeffs,
    "so3_blocks": so3_blocks,
    "so3_layout": so3_layout,
    "rotate_s2_coeffs": lambda l: rotate_s2_coeffs(torch.zeros(1, 9, dtype=torch.float64), _R[0], l),
    "left_translate_so3_coeffs": lambda l: left_translate_so3_coeffs(torch.zeros(1, 35, dtype=torch.float64), _R[0], l),
    "get_grid_evaluator": lambda l: get_grid_evaluator(l, 1),
    "HealpixGridEvaluator": lambda l: HealpixGridEvaluator(l, 1),
    "dense_grid_logits": lambda l: dense_grid_logits(torch.zeros(1, 35), l, 1),
    "SO3Distribution": lambda l: SO3Distribution(torch.zeros(1, 35), l),
}


@pytest.mark.parametrize("name", LMAX_FUNCTIONS)
@pytest.mark.parametrize("bad", [-1, 1.5, "2", None])
def test_bad_band_limits_are_value_errors_naming_the_argument(name, bad):
    argument = "l" if name == "wigner_D" else "lmax"
    with pytest.raises(ValueError, match=rf"^{argument} must be an integer >= 0, got {bad!r}"):
        LMAX_FUNCTIONS[name](bad)


def test_wigner_d_accepts_plain_numbers_as_angles():
    D = wigner_D(1, 0.0, math.pi / 2, 0.0)
    assert D.shape == (3, 3) and D.is_floating_point()
    torch.testing.assert_close(D, wigner_D(1, *(torch.tensor(a) for a in (0.0, math.pi / 2, 0.0))))


# ---------------------------------------------------------------------------------- grid levels
def _level_entry_points() -> dict:
    dist = SO3Distribution(torch.zeros(1, N_COEFFS), LMAX)
    R = torch.eye(3)[None]
    return {
        "so3_healpix_grid": lambda lv: so3_healpix_grid(lv),
        "so3_healpix_grid_angles": lambda lv: so3_healpix_grid_angles(lv),
        "dense_grid_logits": lambda lv: dense_grid_logits(dist.coeffs, LMAX, lv),
        "get_grid_evaluator": lambda lv: get_grid_evaluator(LMAX, lv),
        "HealpixGridEvaluator": lambda lv: HealpixGridEvaluator(LMAX, lv),
        "grid_logits": lambda lv: dist.grid_logits(lv),
        "log_prob_grid": lambda lv: dist.log_prob_grid(lv),
        "log_normalizer": lambda lv: dist.log_normalizer(lv),
        "log_prob_at_index": lambda lv: dist.log_prob_at_index(torch.tensor([0]), lv),
        "log_density": lambda lv: dist.log_density(R, lv),
        "mode": lambda lv: dist.mode(lv),
        "mode_refined": lambda lv: dist.mode(lv, refine=True),
        "sample": lambda lv: dist.sample(3, lv),
        "modes": lambda lv: dist.modes(lv),
        "modes_mass_level": lambda lv: dist.modes(lv, mass_level=lv),
        "points_above": lambda lv: dist.points_above(0.1, lv),
        "default_threshold": lambda lv: dist.default_threshold(lv),
        "max_prob": lambda lv: dist.max_prob(lv),
        "nearest_index": lambda lv: so3_healpix_nearest_index(R, lv),
        "so3_grid_size": lambda lv: so3_grid_size(lv),
    }


LEVEL_ENTRY_POINTS = list(_level_entry_points())


@pytest.mark.parametrize("name", LEVEL_ENTRY_POINTS)
def test_too_fine_levels_are_refused_at_once(name):
    entry = _level_entry_points()[name]
    too_fine = [8, 10] if name not in ("nearest_index", "so3_grid_size") else [11, 30]
    if name in ("so3_healpix_grid", "so3_healpix_grid_angles", "dense_grid_logits", "grid_logits", "log_prob_grid"):
        too_fine.append(7)  # dense: one value or matrix per point
    for level in too_fine:
        start = time.perf_counter()
        with pytest.raises(ValueError, match=rf"level={level} is too fine"):
            entry(level)
        assert time.perf_counter() - start < 1.0, (name, level)


def test_too_fine_level_message_gives_points_bytes_and_allowed_range():
    with pytest.raises(ValueError) as info:
        so3_healpix_grid(10)
    message = str(info.value)
    assert "level=10 is too fine for a dense grid of rotation matrices" in message
    assert f"{72 * 8**10:,} points" in message and "TB" in message and "allowed levels are 0..6" in message
    dist = SO3Distribution(torch.zeros(1, N_COEFFS), LMAX)
    with pytest.raises(ValueError, match=r"level=8 is too fine for streamed evaluation: .* 4.83 GB .* 0..7"):
        dist.sample(1, 8)
    with pytest.raises(ValueError, match=r"mass_level=7 is too fine .* 0..6"):
        dist.modes(7, mass_level=7)


@pytest.mark.parametrize("name", LEVEL_ENTRY_POINTS)
@pytest.mark.parametrize("bad", [-1, 2.5, "3", True, None])
def test_negative_and_non_integer_levels_are_refused(name, bad):
    with pytest.raises(ValueError, match=r"level must be an integer in 0..\d+, got"):
        _level_entry_points()[name](bad)


def test_numpy_integer_levels_and_the_finest_allowed_levels_are_accepted():
    assert so3_grid_size(np.int64(2)) == (192, 24)
    assert check_streamed_level(MAX_STREAMED_LEVEL) == 7  # streamed evaluation: up to level 7
    assert check_level(MAX_DENSE_LEVEL, max_level=MAX_DENSE_LEVEL) == 6  # one value per point: up to 6
    assert so3_near_identity_grid(axis_level=0).shape == (37, 3, 3)
    with pytest.raises(ValueError, match=r"axis_level must be an integer"):
        so3_near_identity_grid(axis_level=-1)
    # index arithmetic is not bound by the dense or streamed limits
    index = so3_healpix_nearest_index(torch.eye(3, dtype=torch.float64)[None], 7)
    nearest = so3_healpix_index_to_matrix(index, 7, dtype=torch.float64)
    assert geodesic_distance_deg(nearest, torch.eye(3, dtype=torch.float64)).item() < 1.0


# ------------------------------------------------------------------ image2sphere.checks
@pytest.mark.parametrize("bad", [True, False, -1, 1.0, "1", None])
def test_check_int_refuses_bools_non_integers_and_none_naming_the_key(bad):
    with pytest.raises(ValueError, match=rf"^model\.n must be an integer >= 0, got {re.escape(repr(bad))}$"):
        check_int("model.n", bad)


def test_check_int_minimum_is_inclusive_and_none_needs_allow_none():
    assert check_int("n", 3, 3) == 3 and check_int("n", 0) == 0
    with pytest.raises(ValueError, match=r"^n must be an integer >= 3, got 2$"):
        check_int("n", 2, 3)
    assert check_int("n", None, 1, allow_none=True) is None
    with pytest.raises(ValueError, match=r"^n must be an integer >= 1 or None \(None: all\), got 0$"):
        check_int("n", 0, 1, allow_none=True, note=" (None: all)")
    with pytest.raises(ValueError, match=r"^n must be an integer >= 1, got None$"):
        check_int("n", None, 1)


@pytest.mark.parametrize("bad", [True, -0.5, math.inf, -math.inf, math.nan, "1", None])
def test_check_number_refuses_bools_infinities_nan_and_non_numbers_naming_the_key(bad):
    with pytest.raises(ValueError, match=rf"^loss\.w must be a finite number >= 0, got {re.escape(repr(bad))}$"):
        check_number("loss.w", bad)


def test_check_number_minimum_is_inclusive_and_the_value_comes_back_as_a_float():
    assert check_number("w", 0) == 0.0 and type(check_number("w", 2)) is float
    assert check_number("w", 1.5, minimum=1.5) == 1.5
    with pytest.raises(ValueError, match=r"^w must be a finite number >= 1.5, got 1.4$"):
        check_number("w", 1.4, minimum=1.5)
