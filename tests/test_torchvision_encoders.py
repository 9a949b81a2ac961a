"""``encoder=torchvision``: any torchvision classification model's last spatial feature map feeds the networks
(:class:`image2sphere.nn.TorchvisionEncoder`). Random weights at 32 or 64 px on the CPU; quick tier except
two families (slow)."""

from __future__ import annotations

import sys

import pytest
import torch
from torch import nn

from conftest import TINY, read_metrics, run_module
from image2sphere.checks import ConfigError
from image2sphere.nn import I2S, MatrixFisherNet, TorchvisionEncoder

# each of the encoder's branches in the quick tier (features, RegNet's trunk, Swin's channels last, ViT's
# tokens); two more families of the features branch in the slow one
SLOW = [pytest.mark.slow]
FAMILIES = [pytest.param("convnext_tiny", 64, 768, marks=SLOW), pytest.param("efficientnet_b0", 64, 1280, marks=SLOW),
            ("regnet_y_400mf", 64, 440), ("mobilenet_v3_small", 64, 576), ("swin_t", 64, 768),
            ("vit_b_16", 32, 768)]  # fmt: skip


@pytest.mark.parametrize(("name", "size", "channels"), FAMILIES)
def test_each_family_gives_its_last_feature_map_and_trains_i2s(name, size, channels):
    """Quick. The map has the family's channels and the size ``feature_size`` says (32 px: a ViT-B/16's 2 x 2
    patches, a ConvNeXt's stride 32), evaluation mode changes no BatchNorm statistic while measuring it, and an
    I2S network on it gives a finite loss whose gradient reaches the encoder's first layer."""
    torch.manual_seed(0)
    encoder = TorchvisionEncoder(name, image_size=size)
    assert encoder.out_channels == channels and encoder.training
    before = {k: v.clone() for k, v in encoder.state_dict().items() if "running" in k}
    h, w = encoder.feature_size(size)
    assert all(torch.equal(v, encoder.state_dict()[k]) for k, v in before.items())
    out = encoder(torch.randn(2, 3, size, size))
    assert out.shape == (2, channels, h, w) and torch.isfinite(out).all()
    if name.startswith("vit"):
        assert (h, w) == (size // 16, size // 16)  # the grid of patches
    net = I2S(
        encoder,
        image_size=size,
        lmax=2,
        sphere_channels=8,
        so3_channels=4,
        activation_resolution=4,
        output_init="random",
    )  # (zero, the default, passes no gradient back at the start)
    loss = net.loss(net(torch.randn(2, 3, size, size)), torch.eye(3).expand(2, 3, 3), 1).mean()
    loss.backward()
    first = next(p for p in encoder.parameters() if p.ndim > 1)
    assert torch.isfinite(loss) and first.grad is not None and first.grad.abs().sum() > 0


def test_a_feature_vector_network_pools_the_map_of_any_family():
    """Quick. A baseline that takes a feature vector (matrix Fisher) on a non-ResNet map."""
    net = MatrixFisherNet(TorchvisionEncoder("mobilenet_v3_small", image_size=64), 64, hidden=8)
    assert torch.isfinite(net.loss(net(torch.randn(2, 3, 64, 64)), torch.eye(3).expand(2, 3, 3), 1)).all()


def test_unknown_models_weights_and_families_are_refused_in_one_line(tmp_path):
    with pytest.raises(ConfigError, match="encoder.name='convnext_tinny' is no torchvision classification model"):
        TorchvisionEncoder("convnext_tinny")
    with pytest.raises(ConfigError, match="unknown torchvision weights 'IMAGENET9K' for efficientnet_b0"):
        TorchvisionEncoder("efficientnet_b0", weights="IMAGENET9K")
    with pytest.raises(ConfigError, match="its feature map is not known here"):
        TorchvisionEncoder("googlenet")
    saved = tmp_path / "mine.pt"
    torch.save(nn.Linear(2, 2).state_dict(), saved)
    with pytest.raises(ConfigError, match="does not fit mobilenet_v3_small"):
        TorchvisionEncoder("mobilenet_v3_small", weights=str(saved))


def test_a_local_weights_file_is_loaded_without_its_classifier(tmp_path):
    """Quick. The state dict of a whole torchvision model, classifier included, is what a local file holds."""
    from torchvision import models

    torch.manual_seed(1)
    full = models.get_model("mobilenet_v3_small", weights=None)
    torch.save(full.state_dict(), tmp_path / "mobilenet.pth")
    encoder = TorchvisionEncoder("mobilenet_v3_small", weights=str(tmp_path / "mobilenet.pth"))
    torch.testing.assert_close(encoder.body[0][0].weight, full.features[0][0].weight, rtol=0, atol=0)


def test_train_runs_with_a_torchvision_backbone_from_the_command_line(tmp_path):
    """Quick. ``python -m src.train encoder=torchvision encoder.name=mobilenet_v3_small``, one batch."""
    run = tmp_path / "run"
    argv = [sys.executable, "-m", "src.train", *TINY, "encoder=torchvision", "encoder.name=mobilenet_v3_small",
            "trainer.fast_dev_run=true", "logger=none", f"paths.data_dir={tmp_path / 'data'}",
            f"paths.log_dir={tmp_path / 'logs'}", f"hydra.run.dir={run}"]  # fmt: skip
    proc = run_module(argv)
    assert "mobilenet_v3_small, random initialisation" in proc.stdout + proc.stderr
    assert read_metrics(run)["n_images"] > 0
