"""PoseEstimationModule: loss and evaluation against dense references, NaN handling, checkpoint state."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from torch import nn

from conftest import haar_rotations
from image2sphere.distributions import LOG_UNIFORM_DENSITY
from image2sphere.metrics import log_density_from_grid_logits, min_angular_error_deg
from image2sphere.so3 import dense_grid_logits, n_so3_coeffs, so3_healpix_index_to_matrix, so3_healpix_nearest_index
from image2sphere.training import NonFiniteLossError, PoseEstimationModule

LMAX = 2


class TinyNet(nn.Module):
    """Mean colour -> SO(3) coefficients: enough to exercise the module."""

    def __init__(self, lmax: int = LMAX, scale: float = 1.0):
        super().__init__()
        self.lmax = lmax
        self.linear = nn.Linear(3, n_so3_coeffs(lmax))
        self.scale = scale

    def forward(self, images):
        return self.scale * self.linear(images.mean(dim=(-1, -2)))


def _module(net=None, **kw) -> PoseEstimationModule:
    opt = functools.partial(torch.optim.SGD, lr=0.1)
    levels = {"train_grid_level": 2, "val_grid_level": 2, "eval_grid_level": 2, "spread_grid_level": 1}
    return PoseEstimationModule(net or TinyNet(), optimizer=opt, **(levels | {"class_names": ["a", "b"]} | kw))


def _eval_batch(B: int = 4, M: int = 3) -> dict:
    torch.manual_seed(0)
    return {
        "image": torch.randn(B, 3, 8, 8),
        "class_index": torch.tensor([0, 1, 0, 1])[:B],
        "index": torch.arange(B),
        "rotations": haar_rotations(B * M, seed=9, dtype=torch.float32).reshape(B, M, 3, 3),
        "mask": torch.tensor([[1, 1, 1], [1, 0, 0], [1, 1, 0], [1, 0, 0]], dtype=torch.bool)[:B],
    }


@pytest.mark.filterwarnings("ignore:You are trying to .self.log")
def test_set_loss_is_the_dense_cross_entropy_averaged_over_the_equivalent_rotations():
    """dataset.label=all: a batch with every equivalent rotation (NaN padding) trains on the dense
    cross-entropy averaged over them, for I2S's own set loss and for the generic one of a bare network;
    it is the mean of the one-label losses, so the random label's loss equals it in expectation."""
    module = _module()
    batch = _eval_batch()
    batch["rotations"] = batch["rotations"].masked_fill(~batch["mask"][..., None, None], float("nan"))
    loss = module.training_step(batch, 0)
    logits = dense_grid_logits(module(batch["image"]).double(), LMAX, 2)  # [B, N]
    per_image = []
    for b in range(4):
        real = batch["rotations"][b][batch["mask"][b]]  # [m, 3, 3]
        target = so3_healpix_nearest_index(real, 2)
        per_image.append(nn.functional.cross_entropy(logits[b].expand(len(real), -1), target))
    assert loss.item() == pytest.approx(torch.stack(per_image).mean().item(), rel=1e-4)
    loss.backward()
    assert module.net.linear.weight.grad.abs().sum() > 0
    first_label = module.training_step({"image": batch["image"], "rotation": batch["rotations"][:, 0]}, 0)
    assert first_label.item() != pytest.approx(loss.item(), rel=1e-3)  # not the rendering rotation's loss
    with pytest.raises(ValueError, match="mask"):
        module.training_step(batch | {"mask": torch.zeros(4, 3, dtype=torch.bool)}, 0)


@pytest.mark.filterwarnings("ignore:You are trying to .self.log")
def test_training_loss_is_dense_cross_entropy_at_nearest_grid_point():
    module = _module()
    batch = {"image": torch.randn(4, 3, 8, 8), "rotation": haar_rotations(4, seed=1, dtype=torch.float32)}
    loss = module.training_step(batch, 0)
    coeffs = module(batch["image"]).double()
    logits = dense_grid_logits(coeffs, LMAX, 2)
    target = so3_healpix_nearest_index(batch["rotation"], 2)
    expected = nn.functional.cross_entropy(logits, target)
    assert loss.item() == pytest.approx(expected.item(), rel=1e-4)
    loss.backward()  # the streamed loss is differentiable
    assert module.net.linear.weight.grad.abs().sum() > 0


def _paper_protocol_log_likelihood(probabilities, grid, targets, mask, class_index) -> float:
    """The SYMSOL log likelihood as the paper's protocol computes it, written here from its description
    with numpy and scipy alone: each (image, equivalent rotation) pair is read at the grid point whose
    quaternion has the largest ``|dot|`` with the rotation's, ``log(p * N / pi^2)``; an image's value is
    the mean over its equivalent set (the expectation of one equivalent drawn at random per image, as
    the paper's code draws it, and IPDF's mean over all pairs where the sets have one size); a class's
    value the mean over its images; the headline the mean over classes."""
    grid_quats = Rotation.from_matrix(grid).as_quat()  # [N, 4]
    per_class: dict[int, list[float]] = {}
    for b in range(len(targets)):
        real = Rotation.from_matrix(targets[b][mask[b]]).as_quat()  # [m, 4]
        nearest = np.abs(grid_quats @ real.T).argmax(0)  # [m]
        values = np.log(probabilities[b][nearest] * len(grid) / np.pi**2)
        per_class.setdefault(int(class_index[b]), []).append(float(values.mean()))
    return float(np.mean([np.mean(v) for v in per_class.values()]))


def test_log_likelihood_weighs_every_image_once_as_the_papers_protocol_whatever_its_set_size():
    """Sets of 3, 1, 2 and 1 equivalent rotations: the test's log likelihood is the mean over images of
    each image's mean over its set (the paper's protocol, re-computed independently), not the mean over
    all (image, rotation) pairs, which lets the images with large sets outweigh the others."""
    module = _module(TinyNet(scale=5.0))
    batch = _eval_batch()
    module._record(module._evaluate(batch, level=2, spread_level=None))
    got = module._summarize()
    with torch.no_grad():
        logits = dense_grid_logits(module(batch["image"]).double(), LMAX, 2)  # [B, N]
    probabilities = torch.softmax(logits, dim=1).numpy()
    grid = so3_healpix_index_to_matrix(torch.arange(logits.shape[1]), 2, dtype=torch.float64).numpy()
    targets, mask = batch["rotations"].double().numpy(), batch["mask"].numpy()
    expected = _paper_protocol_log_likelihood(probabilities, grid, targets, mask, batch["class_index"].numpy())
    assert got["log_likelihood"] == pytest.approx(expected, rel=1e-5)
    # the mean over all pairs of each class: a different number on these sets
    ll = log_density_from_grid_logits(logits, batch["rotations"].double(), batch["mask"], 2)  # [B, M]
    pairs = [float(ll[batch["class_index"] == c].nan_to_num(0).sum() / batch["mask"][batch["class_index"] == c].sum())
             for c in (0, 1)]  # fmt: skip
    assert abs(float(np.mean(pairs)) - expected) > 1e-3


def test_evaluation_matches_dense_reference():
    module = _module(TinyNet(scale=5.0))
    batch = _eval_batch()
    out = module._evaluate(batch, level=2, spread_level=1)
    coeffs = module(batch["image"]).double()
    logits = dense_grid_logits(coeffs, LMAX, 2)
    ll = log_density_from_grid_logits(logits, batch["rotations"].double(), batch["mask"], 2)
    torch.testing.assert_close(out["ll_sum"].double(), ll.nan_to_num(0.0).sum(1), rtol=1e-4, atol=1e-4)
    assert out["ll_count"].tolist() == [3, 1, 2, 1]
    pred = so3_healpix_index_to_matrix(logits.argmax(1), 2)
    err = min_angular_error_deg(pred, batch["rotations"].double(), batch["mask"])
    torch.testing.assert_close(out["error_deg"].double(), err, atol=1e-3, rtol=0)
    assert (out["spread"] > 0).all() and (out["spread"] < 180).all()


def test_uniform_model_scores_log_uniform_density():
    net = TinyNet()
    nn.init.zeros_(net.linear.weight)
    nn.init.zeros_(net.linear.bias)
    module = _module(net)
    module.test_step(_eval_batch(), 0)
    metrics = module._summarize()
    assert metrics["log_likelihood"] == pytest.approx(LOG_UNIFORM_DENSITY, abs=1e-5)
    assert metrics["log_likelihood/a"] == pytest.approx(LOG_UNIFORM_DENSITY, abs=1e-5)
    assert set(metrics) >= {"acc15/b", "median_error_deg", "loss"}


def test_nan_loss_stops_with_clear_error():
    module = _module(TinyNet(scale=math.nan))
    batch = {"image": torch.randn(2, 3, 8, 8), "rotation": haar_rotations(2, seed=1, dtype=torch.float32)}
    with pytest.raises(NonFiniteLossError, match="training loss is nan .* Lower model.optimizer.lr"):
        module.training_step(batch, 7)


def test_checkpoint_keeps_class_names():
    ckpt: dict = {}
    _module().on_save_checkpoint(ckpt)
    restored = _module(class_names=None)
    restored.on_load_checkpoint(ckpt)
    assert restored.class_names == ["a", "b"]


def test_step_randomness_depends_only_on_seed_and_global_step(monkeypatch):
    def draw(module, step: int) -> torch.Tensor:
        monkeypatch.setattr(type(module), "global_step", property(lambda self: step))
        module.on_train_batch_start({}, 0)
        return torch.rand(4)

    draws = []
    for before in (0, 7):  # whatever was drawn earlier (sanity checks, other loaders) does not matter
        torch.manual_seed(3)
        module = _module()
        module.on_fit_start()
        torch.rand(before)
        draws.append(draw(module, 5))
    torch.testing.assert_close(draws[0], draws[1])
    assert not torch.equal(draw(module, 6), draws[0])  # every step has its own draws
    torch.manual_seed(4)  # another run seed
    other = _module()
    other.on_fit_start()
    assert not torch.equal(draw(other, 5), draws[0])


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"train_grid_level": 11}, "model.train_grid_level"),
        ({"eval_grid_level": -1}, "model.eval_grid_level"),
        ({"scheduler_interval": "batch"}, "scheduler_interval"),
    ],
)
def test_invalid_config_values_name_the_key(kw, match):
    with pytest.raises(ValueError, match=match):
        _module(**kw)


def test_network_without_lmax_is_rejected():
    with pytest.raises(ValueError, match=r"\.lmax"):
        PoseEstimationModule(nn.Linear(3, 3), optimizer=functools.partial(torch.optim.SGD, lr=0.1))
