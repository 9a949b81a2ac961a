"""Projector, encoder, the composed I2S variants, and the torchvision guard."""

import math
import subprocess
import sys

import pytest
import torch
from e3nn import o3

from image2sphere.distributions import SO3Distribution
from image2sphere.nn import I2S, FourierMLP, HarmonicS2Projector, ResNetEncoder, SpatialS2Projector
from image2sphere.so3 import n_s2_coeffs, n_so3_coeffs, random_rotations, s2_healpix_grid
from image2sphere.so3.wigner import rotate_s2_coeffs


def _identity_projector(**kwargs):
    proj = SpatialS2Projector(1, 7, sphere_channels=1, lmax=4, activation=False, **kwargs)
    with torch.no_grad():
        proj.conv.weight.fill_(1.0)
        proj.conv.bias.zero_()
    return proj.eval()


def test_projector_maps_the_image_centre_to_the_pole():
    proj = _identity_projector()
    fmap = torch.zeros(1, 1, 7, 7)
    fmap[..., 3, 3] = 1.0
    signal = proj.project(fmap)[0, 0]  # [K]
    assert proj.beta[signal.argmax()] == proj.beta.min()  # the grid points nearest the +y pole
    assert signal[proj.beta > math.radians(60)].abs().max() < 1e-3 * signal.max()


def test_projector_image_corners_map_to_nothing():
    proj = _identity_projector()
    fmap = torch.zeros(1, 1, 7, 7)
    corners = [(0, 0), (0, 1), (1, 0), (0, 6), (0, 5), (1, 6), (6, 0), (5, 0), (6, 1), (6, 6), (5, 6), (6, 5)]
    for r, c in corners:  # cells whose centre lies outside the image's inscribed circle
        fmap[..., r, c] = 1.0
    assert proj.project(fmap).abs().max() == 0
    assert int((proj.inside == 0).sum()) == len(corners)
    fmap[..., 3, 0] = 1.0  # the middle of an edge lies on the disk: it is read
    assert proj.project(fmap).abs().max() > 0


def test_projector_hemisphere_and_taper():
    proj = _identity_projector()
    assert proj.beta.max() <= math.pi / 2 + 1e-6
    fmap = torch.ones(1, 1, 7, 7)
    signal = proj.project(fmap)[0, 0]
    # interpolation weights sum to one, so a constant map gives the taper profile
    taper = ((math.pi / 2 - proj.beta) / (math.pi / 2 - math.radians(75))).clamp(0, 1)
    torch.testing.assert_close(signal, taper, atol=1e-5, rtol=1e-5)


def test_projector_subsets_points_only_in_training():
    proj = SpatialS2Projector(8, 7, sphere_channels=4, lmax=3, n_subset=20)
    fmap = torch.randn(2, 8, 7, 7)
    proj.train()
    torch.manual_seed(0)
    pts = proj.sample_points()
    assert len(pts) == 20 and len(set(pts.tolist())) == 20
    torch.manual_seed(0)
    a = proj(fmap)
    torch.manual_seed(1)
    b = proj(fmap)
    assert not torch.allclose(a, b)
    proj.eval()
    assert len(proj.sample_points()) == proj.n_points
    torch.manual_seed(0)
    c = proj(fmap)
    torch.manual_seed(1)
    torch.testing.assert_close(c, proj(fmap))
    assert c.shape == (2, 4, n_s2_coeffs(3))


def test_projector_subset_in_eval_draws_in_every_forward_pass():
    """``subset_in_eval`` (the original code's forward): in eval mode too, each pass projects a random
    subset, the one ``torch.randperm`` draws, and the result equals the projection on those points."""
    proj = SpatialS2Projector(8, 7, sphere_channels=4, lmax=3, n_subset=20, normalization="sqrt", subset_in_eval=True)
    fmap = torch.randn(2, 8, 7, 7)
    proj.eval()
    torch.manual_seed(3)
    pts = proj.sample_points()
    assert len(pts) == 20 and len(set(pts.tolist())) == 20
    torch.manual_seed(3)
    a = proj(fmap)
    torch.manual_seed(4)
    assert not torch.allclose(a, proj(fmap))
    # the same draw in training mode: the same coefficients
    proj.train()
    torch.manual_seed(3)
    torch.testing.assert_close(a, proj(fmap))


def test_projector_rejects_bad_input():
    with pytest.raises(ValueError, match="n_subset"):
        SpatialS2Projector(8, 7, n_subset=1000)
    with pytest.raises(ValueError, match="subset_in_eval"):
        SpatialS2Projector(8, 7, subset_in_eval=True)
    with pytest.raises(ValueError, match="subset_in_eval"):
        SpatialS2Projector(8, 7, n_subset=20, subset_in_eval="yes")
    with pytest.raises(ValueError, match="feature map must have shape"):
        SpatialS2Projector(8, 7, sphere_channels=4, lmax=2)(torch.randn(1, 8, 6, 6))


def test_harmonic_projector_shape():
    out = HarmonicS2Projector(16, sphere_channels=3, lmax=2, hidden_channels=8)(torch.randn(2, 16, 5, 5))
    assert out.shape == (2, 3, n_s2_coeffs(2))


def test_harmonic_projector_relu_on_the_sphere_is_rotation_equivariant_and_a_relu():
    """The Fourier projection's ReLU (e3nn's S2Activation) reads our coefficients in e3nn's basis: rotating
    the MLP's signal rotates the output (up to its grid's sampling error), and the output's degree 0 is a
    fixed multiple of the mean of relu(f) over the sphere, computed densely on a HEALPix grid."""
    lmax = 4
    torch.manual_seed(0)
    act = HarmonicS2Projector(8, sphere_channels=3, lmax=lmax, hidden_channels=8).act.double()
    coeffs = torch.randn(2, 3, n_s2_coeffs(lmax), dtype=torch.float64)  # [B, S, (L+1)^2]
    R = random_rotations(1, generator=torch.Generator().manual_seed(1), dtype=torch.float64)[0]
    with torch.no_grad():
        out = act(coeffs)
        rotated = act(rotate_s2_coeffs(coeffs, R, lmax))
    error = (rotated - rotate_s2_coeffs(out, R, lmax)).abs().max() / out.abs().max()
    assert error < 2e-2, error  # measured 9e-3 at resolution 20; rotating the output by R^T gives 0.86
    alpha, beta = s2_healpix_grid(6, dtype=torch.float64)  # 49,152 equal-area points
    Y = o3.spherical_harmonics_alpha_beta(list(range(lmax + 1)), alpha, beta, normalization="component")
    dense_mean = torch.relu(coeffs @ Y.T).mean(-1)  # [B, S]
    ratio = out[..., 0] / dense_mean
    # e3nn scales the ReLU to keep a unit normal's second moment: about sqrt 2 (measured 1.403-1.420); with
    # e3nn's "component" grids instead of "norm" the ratio ranges over 0.21-1.03
    torch.testing.assert_close(ratio, torch.full_like(ratio, ratio.mean().item()), rtol=2e-2, atol=0)
    assert 1.3 < ratio.mean() < 1.5


@pytest.mark.parametrize("depth,channels", [(18, 512), (50, 2048)])
def test_encoder_feature_shape(depth, channels):
    enc = ResNetEncoder(depth).eval()
    assert enc.out_channels == channels
    assert enc.feature_size(224) == (7, 7)
    for size in [(224, 224), (97, 130)]:
        with torch.no_grad():
            out = enc(torch.zeros(1, 3, *size))
        assert out.shape == (1, channels, *enc.feature_size(size))


def test_encoder_loads_a_local_weights_file(tmp_path):
    from torchvision.models import resnet18

    torch.manual_seed(3)
    full = resnet18()
    path = tmp_path / "r18.pth"
    torch.save(full.state_dict(), path)
    enc = ResNetEncoder(18, weights=str(path))
    torch.testing.assert_close(enc.body[0].weight, full.conv1.weight)
    torch.testing.assert_close(enc.body[7][1].conv2.weight, full.layer4[1].conv2.weight)


def test_encoder_weights_errors(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="does not exist"):
        ResNetEncoder(18, weights=str(tmp_path / "missing.pth"))
    bad = tmp_path / "bad.pth"
    bad.write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="could not be read"):
        ResNetEncoder(18, weights=str(bad))
    wrong = tmp_path / "r50.pth"
    from torchvision.models import resnet50

    torch.save(resnet50().state_dict(), wrong)
    with pytest.raises(ValueError, match="does not fit resnet18"):
        ResNetEncoder(18, weights=str(wrong))
    with pytest.raises(ValueError, match="unknown torchvision weights"):
        ResNetEncoder(18, weights="NOT_A_WEIGHT")
    with pytest.raises(ValueError, match="depth"):
        ResNetEncoder(19)
    # a known name whose download fails (no network here, and never attempted by the test)
    from torchvision.models import ResNet18_Weights

    def offline(self, *args, **kwargs):
        raise OSError("no network")

    monkeypatch.setattr(type(ResNet18_Weights.IMAGENET1K_V1), "get_state_dict", offline)
    with pytest.raises(RuntimeError, match="could not load torchvision weights.*weights=null"):
        ResNetEncoder(18, weights="IMAGENET1K_V1")


VARIANTS = [
    dict(),
    dict(projector="harmonic", sphere_channels=32),
    dict(filter="spatial"),
    dict(projector="harmonic", filter="spatial", sphere_channels=32),
    dict(n_so3_conv=0),
    dict(n_so3_conv=2),
    dict(lmax=2),
    dict(num_classes=3),
]


@pytest.fixture(scope="module")
def resnet18():
    return ResNetEncoder(18)


@pytest.mark.parametrize("kwargs", VARIANTS, ids=lambda k: ",".join(f"{a}={b}" for a, b in k.items()) or "i2s")
def test_every_i2s_variant_trains_on_cpu(kwargs, resnet18):
    torch.manual_seed(0)
    model = I2S(resnet18, image_size=224, activation_resolution=6, **kwargs)
    images = torch.randn(2, 3, 224, 224)
    classes = torch.tensor([0, 2]) if kwargs.get("num_classes") else None
    coeffs = model(images, classes)
    assert coeffs.shape == (2, n_so3_coeffs(kwargs.get("lmax", 6)))
    target = torch.tensor([5, 17])

    def gradients() -> dict[str, torch.Tensor | None]:
        loss = torch.nn.functional.cross_entropy(
            SO3Distribution(model(images, classes), model.lmax).grid_logits(1), target
        )
        model.zero_grad()
        loss.backward()
        assert torch.isfinite(loss)
        return {n: p.grad for n, p in model.named_parameters() if p.requires_grad}

    # the last convolution starts at zero (output_init="zero"): the first prediction is uniform and
    # only that layer gets a gradient; after one step every layer does
    last = next(f"{n}.weight" for n, m in model.named_modules() if m is model.output_layer)
    assert torch.equal(coeffs, torch.zeros_like(coeffs))
    grads = gradients()
    assert grads[last].abs().sum() > 0
    # one step of everything after the (module-shared) encoder
    torch.optim.Adam([p for n, p in model.named_parameters() if not n.startswith("encoder.")], lr=1e-3).step()
    grads = gradients()
    for name in [last, "s2_conv.weight", "encoder.body.0.weight"]:
        assert grads[name] is not None and grads[name].abs().sum() > 0, name
    assert all(g is None or torch.isfinite(g).all() for g in grads.values())


def test_fourier_mlp_and_distribution(resnet18):
    model = FourierMLP(resnet18, image_size=64, lmax=4, hidden=[32, 16])
    coeffs = model(torch.randn(3, 3, 64, 64))
    assert coeffs.shape == (3, n_so3_coeffs(4))
    dist = model.distribution(torch.randn(3, 3, 64, 64))
    assert isinstance(dist, SO3Distribution) and dist.grid_logits(0).shape == (3, 72)


def test_model_bad_input(resnet18):
    with pytest.raises(ValueError, match="n_so3_conv"):
        I2S(resnet18, n_so3_conv=3)
    with pytest.raises(ValueError, match="projector"):
        I2S(resnet18, projector="fourier")
    with pytest.raises(ValueError, match="degree_power must be a number >= 0, got -1"):
        FourierMLP(resnet18, image_size=64, lmax=2, degree_power=-1)
    with pytest.raises(ValueError, match="degree_power must be a number >= 0, got True"):
        HarmonicS2Projector(8, lmax=2, degree_power=True)
    model = I2S(resnet18, image_size=64, num_classes=2, sphere_channels=8, activation_resolution=4, lmax=2)
    with pytest.raises(ValueError, match="pass class_index"):
        model(torch.randn(1, 3, 64, 64))
    with pytest.raises(ValueError, match="class_index"):
        model(torch.randn(1, 3, 64, 64), torch.tensor([2]))
    with pytest.raises(ValueError, match="images must have shape"):
        model(torch.randn(1, 64, 64))


@pytest.mark.parametrize("scaling", ["imagenet", "unit"])
def test_input_scaling_gives_the_encoder_pixels_over_255_or_the_input_unchanged(scaling, resnet18):
    """``input_scaling="unit"``: the encoder sees a real rendered uint8 image as ``pixels / 255``, though
    the network gets it ImageNet-normalised as the loaders give it; ``"imagenet"``: the input itself."""
    from image2sphere.data.common import normalize_images
    from image2sphere.data.raycast import render
    from image2sphere.nn.base import unscale_imagenet

    pixels = render("cube", random_rotations(2, generator=torch.Generator().manual_seed(0)), image_size=64)
    assert pixels.dtype == torch.uint8 and pixels.shape == (2, 64, 64, 3) and pixels.max() > 100
    images = normalize_images(pixels)  # [2, 3, 64, 64], what the data loaders hand the network
    unit = pixels.movedim(-1, -3).to(torch.float32) / 255
    torch.testing.assert_close(unscale_imagenet(images), unit, atol=1e-6, rtol=0)

    model = I2S(resnet18, image_size=64, lmax=2, sphere_channels=8, activation_resolution=4, input_scaling=scaling)
    assert model.input_scaling == scaling
    seen = []
    hook = model.encoder.register_forward_pre_hook(lambda module, args: seen.append(args[0]))
    try:
        with torch.no_grad():
            model(images)
    finally:
        hook.remove()
    (got,) = seen
    if scaling == "unit":
        torch.testing.assert_close(got, unit, atol=1e-6, rtol=0)
    else:
        assert torch.equal(got, images)


def test_input_scaling_is_refused_with_its_key(resnet18):
    for value in ("pixels", None, 255):
        with pytest.raises(ValueError, match=r"model\.net\.input_scaling must be one of \('imagenet', 'unit'\)"):
            I2S(resnet18, image_size=64, lmax=2, sphere_channels=8, input_scaling=value)
    model = I2S(resnet18, image_size=64, lmax=2, sphere_channels=8, activation_resolution=4, input_scaling="unit")
    with pytest.raises(ValueError, match=r"images must have shape \(batch, 3, H, W\), got \(1, 64, 64\)"):
        model(torch.randn(1, 64, 64))  # not broadcast against the channels' mean and std


def _run(code: str) -> str:
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout


def test_torchvision_guard_makes_torchvision_and_lightning_importable():
    out = _run(
        "import image2sphere, torch, torchvision, lightning\n"
        "from torchvision.models import resnet18\n"
        "print(resnet18().eval()(torch.zeros(1, 3, 64, 64)).shape[-1])\n"
        "print(hasattr(torch.ops.torchvision, 'nms'))\n"
    )
    assert out.split() == ["1000", "True"]


def test_torchvision_guard_is_a_noop_where_the_extension_loads():
    out = _run(
        "from image2sphere import _torchvision_guard as g\n"
        "g._library = None\n"
        "import sys; [sys.modules.pop(m) for m in list(sys.modules) if m.startswith('torchvision')]\n"
        "g._extension_loads = lambda: True\n"
        "print(g.install(), g._library)\n"
    )
    assert out.split() == ["False", "None"]
    # once torchvision is imported (here: a stand-in module) it is too late and nothing is done
    out = _run(
        "import sys, types\n"
        "from image2sphere import _torchvision_guard as g\n"
        "print(g.install())\n"
        "g._library = None\n"
        "sys.modules['torchvision'] = types.ModuleType('torchvision')\n"
        "print(g.install(), g._library)\n"
    )
    assert out.split() == ["False", "False", "None"]
