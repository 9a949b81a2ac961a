"""Every method learns: a short overfit on a few rendered images makes its own training loss fall.

Each method is built from its real ``conf/model/<name>.yaml`` (composed with Hydra, small sizes), so
a wrong sign, a detached parameter, a loss that ignores the label or an output layer that cannot
move would leave the loss where it started.
"""

from __future__ import annotations

import statistics

import pytest
import torch
from hydra.utils import instantiate

from image2sphere.data.common import normalize_images
from image2sphere.data.raycast import render
from image2sphere.so3 import random_rotations
from test_configs import POINT_REGRESSORS, compose_cfg, options

STEPS = 40
# small per-method settings that keep a step cheap on a CPU (the method itself is unchanged)
SMALL = {"ipdf": ["model.net.n_queries=256", "model.net.hidden=64"]}


@pytest.fixture(scope="module")
def images_and_rotations():
    rotations = random_rotations(8, generator=torch.Generator().manual_seed(0))
    images = normalize_images(render("cube", rotations, image_size=32, supersample=1))
    return images, rotations


# every method; of I2S's architecture variants only I2S itself (the variants share its loss and
# output, and tests/test_nn_models.py checks each variant's layers), but the icosahedral group version,
# which has its own output and loss
METHODS = [m for m in options("model") if not m.startswith("i2s_") or m == "i2s_icosahedral"]


@pytest.mark.slow
@pytest.mark.parametrize("model", METHODS)
def test_training_loss_falls_when_overfitting_a_few_images(tmp_path, model, images_and_rotations):
    images, rotations = images_and_rotations
    overrides = [f"model={model}", "lmax=2", "train_grid_level=2", "dataset.image_size=32", "encoder=resnet18"]
    cfg = compose_cfg(tmp_path, overrides + SMALL.get(model, []))
    torch.manual_seed(0)
    net = instantiate(cfg.model.net)
    net.train()
    optimizer = instantiate(cfg.model.optimizer)(params=net.parameters())  # the run's: Adam, lr 1e-3, fused
    losses = []
    for _ in range(STEPS):
        loss = net.loss(net(images), rotations, 2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    # the median of the last steps: the density families' losses can spike for a step when a sharp
    # distribution is briefly wrong (Bingham with 2 threads: ..., -1.96, -3.24, 5.67)
    first, last = sum(losses[:3]) / 3, statistics.median(losses[-8:])
    assert all(map(torch.isfinite, map(torch.tensor, losses))), losses
    # the loss falls by a clear margin: half a nat for the log likelihoods, a quarter of the start for
    # the point regressors' losses (distances, or a distance plus a cross-entropy) and the Wigner-D
    # regression's mean squared error
    margin = 0.25 * first if model in POINT_REGRESSORS | {"wigner_regression"} else 0.5
    assert last < first - margin, (model, first, last)


@pytest.mark.slow
def test_every_method_refuses_labels_of_another_batch_with_one_message(tmp_path, images_and_rotations):
    """One rule for a training label (image2sphere.rotation_sets.check_labels): every method's loss refuses
    ``rotation`` of another shape than ``(B, 3, 3)`` with the same message, before it computes anything."""
    images, rotations = images_and_rotations
    wrong = {}
    for model in METHODS:
        overrides = [f"model={model}", "lmax=2", "train_grid_level=2", "encoder=resnet18", "dataset.image_size=32"]
        net = instantiate(compose_cfg(tmp_path / model, overrides + SMALL.get(model, [])).model.net)
        output = net(images[:2])
        for bad in (rotations[:3], rotations[:2, :2], rotations[0]):
            expected = f"rotation must have shape (2, 3, 3), got {tuple(bad.shape)}"
            try:
                net.loss(output, bad, 2)
                wrong[model, tuple(bad.shape)] = "nothing raised"
            except Exception as e:  # noqa: BLE001 (any other error is a finding too)
                if not isinstance(e, ValueError) or str(e) != expected:
                    wrong[model, tuple(bad.shape)] = f"{type(e).__name__}: {e}"
    assert wrong == {}, "\n".join(f"{k}: {v[:150]}" for k, v in wrong.items())
