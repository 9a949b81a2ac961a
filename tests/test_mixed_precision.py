"""Mixed precision (``trainer.precision=bf16-mixed`` / ``16-mixed``) is safe by construction.

Under ``torch.autocast`` only the encoder may compute in reduced precision; the head of every method,
its distribution (log densities, grid logsumexp, normalisers) and its loss compute in float32
(:mod:`image2sphere.precision`). Every network here is built from the real ``conf/model/*.yaml``, made
small (ResNet-18, 32 px images, lmax 2), on the CPU with bfloat16 autocast.

* The sharp test: given the same float32 features, everything after the encoder gives the same numbers
  under autocast as without it (measured: bit-identical for every method; allowed: 1e-6). A control
  switches the mechanism off and shows that the same comparison then fails for every method.
* The whole network under autocast: float32 outputs, losses and log likelihoods, close to the float32
  run within the error of the bfloat16 encoder.
"""

from __future__ import annotations

import functools
import math
import re
import warnings
from contextlib import nullcontext
from pathlib import Path

import lightning.pytorch as pl
import pytest
import torch
from hydra import compose, initialize
from hydra.core.global_hydra import GlobalHydra
from hydra.utils import instantiate
from torch import nn
from torch.utils.data import DataLoader

import image2sphere.precision as precision
from conftest import haar_rotations
from image2sphere.distributions.base import PoseDistribution
from image2sphere.nn import FourierMLP, MatrixFisherNet, ResNetEncoder
from image2sphere.nn.base import Float32Head, PoseNetwork
from image2sphere.training import PoseEstimationModule, register_resolvers

CONF = Path(__file__).resolve().parents[1] / "conf"
MODELS = sorted(p.stem for p in (CONF / "model").glob("*.yaml"))
IMAGE_SIZE, LEVEL = 32, 2
SMALL = ["lmax=2", f"dataset.image_size={IMAGE_SIZE}", "encoder=resnet18"]

# The sharp test: the head, the distribution and the loss given identical float32 features. Measured
# difference under autocast: 0 (bit-identical) for every method. A head in bfloat16 (its forward
# unwrapped, the distributions still float32) is off by 5e-5 to 6e-3; with the whole mechanism off (the
# control) 17 of the 18 methods fail outright and IPDF's log likelihood is off by 0.24. 1e-6 separates
# the two by more than an order of magnitude.
SHARP_ATOL = 1e-6
# The control must exceed this (10x the sharp tolerance) where it does not fail outright.
CONTROL_MIN = 10 * SHARP_ATOL
# The whole network: bfloat16 keeps 8 bits of mantissa (relative rounding 2^-8 = 3.9e-3), and through
# the ResNet's layers the features differ from float32 by ~1e-2 relative. Measured: outputs, losses and
# log likelihoods within 9e-3 of the float32 run, relative to 1 + |value|; allowed: 5e-2. This does not
# tell a bfloat16 head from a float32 one (its own rounding is smaller than the encoder's): the float32
# dtypes asserted here and the sharp test do.
LOOSE_RTOL = 5e-2


@pytest.fixture(autouse=True)
def _one_thread(single_thread):
    """Every test with one intra-op thread (conftest's ``single_thread``)."""


@functools.cache
def _config(model: str):
    register_resolvers()
    GlobalHydra.instance().clear()
    with initialize(version_base="1.3", config_path="../conf"):
        cfg = compose(config_name="train", overrides=[f"model={model}", *SMALL])
    if "output_init" in cfg.model.net:
        # I2S's last convolution starts at zero, and zeros compare equal in any precision: these tests
        # need an output that the head computes
        cfg.model.net.output_init = "random"
    return cfg


def build(model: str) -> nn.Module:
    """The network of ``conf/model/<model>.yaml``, small, in eval mode (fixed batch-norm statistics)."""
    torch.manual_seed(0)
    return instantiate(_config(model).model.net).eval()


class FixedFeatures(nn.Module):
    """An encoder that returns given features: the network after the encoder sees the same input
    whether or not autocast is on."""

    def __init__(self, encoder: nn.Module, features: torch.Tensor):
        super().__init__()
        self.out_channels = encoder.out_channels
        self._feature_size = encoder.feature_size
        self.features = features

    def feature_size(self, image_size):
        return self._feature_size(image_size)

    def forward(self, images):
        return self.features


def batch(n: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(5)
    images = torch.randn(n, 3, IMAGE_SIZE, IMAGE_SIZE, generator=generator)
    return images, haar_rotations(n, seed=3, dtype=torch.float32)


def evaluate(net: nn.Module, images: torch.Tensor, rotation: torch.Tensor, autocast: bool) -> dict[str, torch.Tensor]:
    """Output, loss and the distribution's numbers for one batch, with or without bfloat16 autocast.
    The global generator is seeded before each step that draws (IPDF's queries)."""
    context = torch.autocast("cpu", dtype=torch.bfloat16) if autocast else nullcontext()
    with context:
        assert torch.is_autocast_enabled("cpu") == autocast
        torch.manual_seed(1)
        out = net(images)
        torch.manual_seed(2)
        result = {"output": out, "loss": net.loss(out, rotation, LEVEL)}
        dist = net.output_distribution(out)
        result["mode"] = dist.mode(LEVEL)
        if dist.has_density:
            result["log_normalizer"] = dist.log_normalizer(LEVEL)  # the grid logsumexp
            result["log_likelihood"] = dist.log_density(rotation[:, None], LEVEL)[:, 0]
            if dist.has_exact_density:  # the closed-form normaliser
                result["exact_log_likelihood"] = dist.exact_log_density(rotation[:, None])[:, 0]
    return result


def with_fixed_features(net: nn.Module, images: torch.Tensor) -> nn.Module:
    with torch.no_grad():
        features = net.encoder(images)  # float32, no autocast
    net.encoder = FixedFeatures(net.encoder, features)
    return net


# ---------------------------------------------------------------------------------------------- the sharp test
@pytest.mark.parametrize("model", MODELS)
def test_everything_after_the_encoder_is_float32_under_autocast(model):
    """Same features in: output, loss, grid logsumexp, log likelihood (grid and closed form) and mode
    under autocast equal the float32 run (measured: bit-identical), and are float32."""
    images, rotation = batch()
    net = with_fixed_features(build(model), images)
    reference, mixed = evaluate(net, images, rotation, False), evaluate(net, images, rotation, True)
    assert set(mixed) == set(reference)
    for key, value in mixed.items():
        assert value.dtype == torch.float32, f"{model}: {key} is {value.dtype} under autocast"
        difference = (value - reference[key]).abs().max().item()
        assert difference <= SHARP_ATOL, f"{model}: {key} differs by {difference:.3g} under autocast"


@pytest.fixture
def drop_caches():
    """For a control that computes under autocast without the mechanism: the tables it caches may be
    built in bfloat16, so they are dropped afterwards and no later test reads them."""
    from image2sphere import metrics
    from image2sphere.distributions import grid_protocol, matrix_fisher
    from image2sphere.so3 import grid_eval

    yield
    for cache in (grid_eval._cached, grid_protocol._grid_rotations, matrix_fisher._half_interval_rule,
                  metrics._flat_grid):  # fmt: skip
        cache.cache_clear()


@pytest.fixture
def mechanism_off(monkeypatch, drop_caches):
    """Every float32 region passes through (it sees no autocast)."""
    monkeypatch.setattr(precision, "current_autocast", lambda: None)


@pytest.mark.parametrize("model", MODELS)
def test_the_sharp_test_fails_with_the_mechanism_off(model, mechanism_off):
    """Control: with the float32 regions switched off (they then see no autocast and pass through), the
    head computes in bfloat16 and the comparison above fails for every method: a result differs by
    more than ``CONTROL_MIN`` or is not float32, or the computation fails outright (rotations computed
    in bfloat16 are not rotations to 1e-4; bfloat16 has no LU on the CPU; the Fourier projection's ReLU on
    the sphere, e3nn's grid transform, rejects bfloat16 inputs; the flow's quaternions underflow to zero).
    Measured: 19 of the 20 methods fail outright, IPDF's log likelihood is off by 0.24."""
    images, rotation = batch()
    net = with_fixed_features(build(model), images)
    reference = evaluate(net, images, rotation, False)  # no autocast: the mechanism makes no difference
    try:
        mixed = evaluate(net, images, rotation, True)
    except (ValueError, NotImplementedError, RuntimeError) as error:
        assert re.search("not a rotation matrix|not orthonormal|BFloat16|quaternions must be finite", str(error)), error
        return
    dtypes = {key: value.dtype for key, value in mixed.items()}
    differences = {key: (value.float() - reference[key]).abs().max().item() for key, value in mixed.items()}
    assert set(dtypes.values()) != {torch.float32} or max(differences.values()) > CONTROL_MIN, (dtypes, differences)


# ---------------------------------------------------------------------------------------------- the whole network
@pytest.mark.parametrize("model", MODELS)
def test_network_under_autocast_is_float32_and_close_to_float32(model):
    """With the real (bfloat16) encoder: float32 results within the encoder's error of the float32 run.
    The mode of a point regressor that picks a bin or anchor by argmax may jump to another one, and a
    grid mode to a neighbouring grid point: only its dtype is checked."""
    images, rotation = batch()
    net = build(model)
    reference, mixed = evaluate(net, images, rotation, False), evaluate(net, images, rotation, True)
    for key, value in mixed.items():
        assert value.dtype == torch.float32, f"{model}: {key} is {value.dtype} under autocast"
        assert torch.isfinite(value).all(), f"{model}: {key} is not finite under autocast"
        if key == "mode":
            continue
        scale = 1 + reference[key].abs().max().item()
        difference = (value - reference[key]).abs().max().item()
        assert difference <= LOOSE_RTOL * scale, f"{model}: {key} differs by {difference:.3g} (scale {scale:.3g})"
    # the encoder itself did run in bfloat16: the features differ, and not by float32 rounding
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        assert net.encoder(images).dtype == torch.bfloat16
        features = net.encode(images)
    assert features.dtype == torch.float32
    assert (features - net.encode(images)).abs().max() > 1e-4


# ---------------------------------------------------------------------------------------------- by construction
def _subclasses(cls: type) -> list[type]:
    out = []
    for sub in cls.__subclasses__():
        out += [sub, *_subclasses(sub)]
    return out


def test_every_network_and_distribution_method_is_a_float32_region():
    """The base classes wrap what each subclass defines: every pose network's forward,
    output_distribution and loss, and every method of every distribution family."""
    import image2sphere.distributions.fourier  # noqa: F401
    import image2sphere.nn  # noqa: F401  (every network and family is defined)

    networks = _subclasses(Float32Head)
    assert {c.__name__ for c in networks} >= {"PoseNetwork", "I2S", "IPDF", "MatrixFisherNet", "RotationRegression"}
    for cls in networks:
        for name in cls.FLOAT32_METHODS:
            method = getattr(cls, name)
            if method is nn.Module.forward:  # not defined anywhere (an abstract base)
                continue
            assert getattr(method, "__float32_region__", False), f"{cls.__name__}.{name} is not a float32 region"
    families = [*PoseDistribution.__mro__[:-1], *_subclasses(PoseDistribution)]  # the grid protocol's too
    assert {c.__name__ for c in families} >= {"SO3Distribution", "Bingham", "ImplicitDistribution", "PointEstimate"}
    for cls in families:
        for name, attr in vars(cls).items():
            if name.startswith("__") and name != "__init__":
                continue
            function = attr.fget if isinstance(attr, property) else getattr(attr, "__func__", attr)
            if callable(function):
                assert getattr(function, "__float32_region__", False), f"{cls.__name__}.{name} is not a float32 region"
    # the tables cached for later calls are built outside autocast
    from image2sphere.distributions import grid_protocol, matrix_fisher
    from image2sphere.so3 import grid_eval

    for cached in (grid_eval._cached, grid_protocol._grid_rotations, matrix_fisher._half_interval_rule):
        assert getattr(cached.__wrapped__, "__float32_region__", False), cached


class TinyEncoder(nn.Module):
    out_channels = 4

    def __init__(self):
        super().__init__()
        self.conv = nn.Conv2d(3, self.out_channels, 3, stride=2, padding=1)

    def feature_size(self, image_size):
        return (math.ceil(image_size / 2),) * 2

    def forward(self, images):
        return self.conv(images)


class ToyDistribution(PoseDistribution):
    """A new family, written without a thought for precision: ``exp(tr(A^T R))`` by a matmul."""

    def __init__(self, A: torch.Tensor):
        self.A = A
        self.batch_size, self.dtype, self.device = A.shape[0], A.dtype, A.device

    def unnormalized_log_density(self, rotations: torch.Tensor) -> torch.Tensor:
        flat = rotations.to(self.dtype).reshape(*rotations.shape[:-2], 9)  # [(B,) K, 9]
        A = self.A.reshape(-1, 9, 1)
        return (flat @ A)[..., 0] if flat.ndim == 3 else (flat[None] @ A)[..., 0]  # [B, K]


class ToyNet(PoseNetwork):
    """A new method, written without a thought for precision: pooled features -> linear -> 9 numbers."""

    def __init__(self):
        super().__init__(TinyEncoder(), 8)
        self.linear = nn.Linear(self.feature_channels, 9)

    def forward(self, images, class_index=None):
        return self.linear(self.pooled_features(images, class_index))

    def output_distribution(self, output):
        return ToyDistribution(output.reshape(-1, 3, 3))

    def loss(self, output, rotation, grid_level):
        return -self.output_distribution(output).log_density(rotation[:, None], grid_level)[:, 0]


def test_a_new_method_computes_in_float32_without_asking():
    """A subclass defined here gets the mechanism: under autocast its encoder runs in bfloat16 and its
    head, distribution and loss in float32, equal to the float32 run given the same features."""
    torch.manual_seed(0)
    net = ToyNet().eval()
    images, rotation = torch.randn(2, 3, 8, 8), haar_rotations(2, seed=1, dtype=torch.float32)
    seen = []
    net.encoder.register_forward_hook(lambda module, args, out: seen.append(out.dtype))
    mixed = evaluate(net, images, rotation, True)
    assert seen == [torch.bfloat16]  # the encoder followed the autocast
    with_fixed_features(net, images)
    reference, mixed = evaluate(net, images, rotation, False), evaluate(net, images, rotation, True)
    for key, value in mixed.items():
        assert value.dtype == torch.float32, key
        assert (value - reference[key]).abs().max() <= SHARP_ATOL, key
    # control: the same head, unwrapped, computes in bfloat16
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert ToyNet.forward.__wrapped__(net, images).dtype == torch.bfloat16
        toy = ToyDistribution(reference["output"].reshape(-1, 3, 3))
        assert ToyDistribution.unnormalized_log_density.__wrapped__(toy, rotation).dtype == torch.bfloat16


def test_without_autocast_nothing_changes():
    """Outside autocast a float32 region calls the function as it is (same objects in, same out); a
    float64 distribution stays float64 under autocast, to the last bit."""
    x = torch.randn(3, dtype=torch.bfloat16)
    assert precision.float32_region(lambda t: t)(x) is x  # not cast: no autocast
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert precision.float32_region(lambda t: t)(x).dtype == torch.float32
    from image2sphere.distributions.matrix_fisher import MatrixFisher

    F = torch.randn(2, 3, 3, dtype=torch.float64)
    rotations = haar_rotations(5, seed=2)
    reference = MatrixFisher(F).exact_log_density(rotations)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        mixed = MatrixFisher(F).exact_log_density(rotations)
    assert mixed.dtype == torch.float64 and torch.equal(mixed, reference)


def test_a_generator_runs_its_steps_in_float32():
    """A generator method (the grid's chunks) computes each step with autocast off; the caller's code
    between the steps keeps its autocast. Control: the unwrapped generator computes in bfloat16."""

    def chunks(n):
        for _ in range(n):
            yield (torch.ones(2, 2) @ torch.ones(2, 2)).dtype

    with torch.autocast("cpu", dtype=torch.bfloat16):
        steps = []
        for dtype in precision.float32_region(chunks)(2):
            steps.append((dtype, torch.is_autocast_enabled("cpu")))
        assert steps == [(torch.float32, True)] * 2
        assert list(chunks(1)) == [torch.bfloat16]


# ---------------------------------------------------------------------------------------------- training module
def _tiny_module(net: nn.Module) -> PoseEstimationModule:
    levels = {"train_grid_level": 2, "val_grid_level": 1, "eval_grid_level": 2, "spread_grid_level": 1}
    return PoseEstimationModule(net, optimizer=functools.partial(torch.optim.SGD, lr=0.01), class_names=["a"], **levels)


def _eval_batch(n: int = 3, m: int = 2) -> dict:
    generator = torch.Generator().manual_seed(7)
    return {
        "image": torch.randn(n, 3, IMAGE_SIZE, IMAGE_SIZE, generator=generator),
        "class_index": torch.zeros(n, dtype=torch.long),
        "index": torch.arange(n),
        "rotations": haar_rotations(n * m, seed=4, dtype=torch.float32).reshape(n, m, 3, 3),
        "mask": torch.ones(n, m, dtype=torch.bool),
    }


@pytest.mark.parametrize("control", [False, True], ids=["float32-region", "control"])
def test_evaluation_metrics_are_float32_under_autocast(control, drop_caches):
    """The module's evaluation (log likelihood, calibration, error, spread) under autocast equals the float32
    run given the same features. Control: ``_evaluate`` without its own float32 region (the network and
    the distribution still have theirs): the metrics computed after the network (the spread's matmul of
    rotations) run in bfloat16 and differ."""
    torch.manual_seed(0)
    batch = _eval_batch()
    net = with_fixed_features(MatrixFisherNet(TinyEncoder(), IMAGE_SIZE, hidden=16).eval(), batch["image"])
    module = _tiny_module(net)
    reference = module._evaluate(batch, 2, 1, calibration=True)
    evaluate_ = PoseEstimationModule._evaluate.__wrapped__ if control else PoseEstimationModule._evaluate
    with torch.autocast("cpu", dtype=torch.bfloat16):
        mixed = evaluate_(module, batch, 2, 1, calibration=True)
    differences = {k: (v.double() - reference[k].double()).abs().max().item() for k, v in mixed.items()}
    if control:
        assert differences["spread"] > CONTROL_MIN, differences
    else:
        assert max(differences.values()) <= SHARP_ATOL, differences


class _Recorder(pl.Callback):
    def __init__(self):
        self.losses: list[float] = []

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
        self.losses.append(float(outputs["loss"]))


@pytest.mark.filterwarnings("ignore::UserWarning")  # Lightning's notes on workers and tiny data sets
def test_lightning_bf16_mixed_trains_and_tests_on_cpu():
    """End to end: ``Trainer(precision="bf16-mixed")``, one training, validation and test batch of a small
    I2S-family network (ResNet-18, Fourier MLP head): the encoder runs in bfloat16, the output is float32,
    the loss and the test metrics are finite."""
    torch.manual_seed(0)
    net = FourierMLP(ResNetEncoder(18), image_size=IMAGE_SIZE, lmax=2, hidden=[16])
    module = _tiny_module(net)
    dtypes: dict[str, set] = {"encoder": set(), "output": set()}
    net.encoder.register_forward_hook(lambda m, a, out: dtypes["encoder"].add(out.dtype))
    net.register_forward_hook(lambda m, a, out: dtypes["output"].add(out.dtype))
    images, rotation = batch(4)
    train = [{"image": images[i], "rotation": rotation[i], "class_index": 0} for i in range(4)]
    evaluation = _eval_batch(4)
    evaluation = [{k: v[i] for k, v in evaluation.items()} for i in range(4)]
    recorder = _Recorder()
    trainer = pl.Trainer(
        precision="bf16-mixed", accelerator="cpu", devices=1, fast_dev_run=1, logger=False,
        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False, callbacks=[recorder],
    )  # fmt: skip
    trainer.fit(module, DataLoader(train, batch_size=4), DataLoader(evaluation, batch_size=4))
    assert recorder.losses and all(math.isfinite(loss) for loss in recorder.losses)
    trainer.test(module, DataLoader(evaluation, batch_size=4), verbose=False)
    assert dtypes == {"encoder": {torch.bfloat16}, "output": {torch.float32}}
    for key in ("log_likelihood", "spread_deg", "median_error_deg", "loss"):
        assert math.isfinite(module.test_metrics[key]), (key, module.test_metrics)


# ---------------------------------------------------------------------------------------------- configuration
@pytest.mark.parametrize("value", ["bf16-mixed", "16-mixed"])
def test_precision_config_passes_through(tmp_path, value):
    """``trainer.precision=<value>`` reaches Lightning's Trainer. 16-mixed (float16 with a gradient scaler)
    is GPU-only: on the CPU Lightning runs bf16-mixed instead and says so."""
    from test_configs import compose_cfg

    cfg = compose_cfg(tmp_path, [f"trainer.precision={value}", "trainer.accelerator=cpu"])
    assert cfg.trainer.precision == value
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        trainer = instantiate(cfg.trainer, logger=False, enable_checkpointing=False)
    assert trainer.precision == "bf16-mixed"
    fell_back = any("not supported on CPU" in str(w.message) for w in caught)
    assert fell_back == (value == "16-mixed")
