"""Recalibration by one temperature (image2sphere.recalibration, docs/evaluation.md#recalibration).

Quick tier: tempering against a dense reference for every kind of family (the Fourier family's own
override, the matrix Fisher family's closed form, the generic grid tempering), its invariants (mode and
order unchanged, composition, temperature 1), the checks of bad temperatures and stored fits, the
fit recovering a known temperature from data drawn at that temperature, and a fit at a bound of the search
kept at T = 1 (degenerate). Whole-run behaviour (the fit after training, the checkpoint, eval's fit/off and
refit, predict) is in the slow tests at the end, on the tiny run.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys

import pytest
import torch

from conftest import haar_rotations, read_metrics, run_module, run_train
from image2sphere.distributions.base import PointEstimate, TemperedDistribution, check_temperature
from image2sphere.distributions.bingham import Bingham
from image2sphere.distributions.fourier import SO3Distribution
from image2sphere.distributions.matrix_fisher import MatrixFisher
from image2sphere.metrics import tie_break_uniforms
from image2sphere.recalibration import Recalibration, ScoredPairs, fit_temperature, score_temperature
from image2sphere.so3.wigner import n_so3_coeffs

LEVEL = 2


def fourier(seed: int = 0, batch: int = 3, lmax: int = 4, scale: float = 0.4) -> SO3Distribution:
    generator = torch.Generator().manual_seed(seed)
    return SO3Distribution(
        scale * torch.randn(batch, n_so3_coeffs(lmax), generator=generator, dtype=torch.float64), lmax
    )


def fisher(seed: int = 0, batch: int = 3, scale: float = 3.0) -> MatrixFisher:
    generator = torch.Generator().manual_seed(seed)
    return MatrixFisher(scale * torch.randn(batch, 3, 3, generator=generator, dtype=torch.float64))


def bingham(seed: int = 0, batch: int = 2) -> Bingham:
    generator = torch.Generator().manual_seed(seed)
    return Bingham.from_output(torch.randn(batch, 8, generator=generator, dtype=torch.float64), num_components=1)


FAMILIES = {"fourier": fourier, "matrix_fisher": fisher, "bingham (generic)": bingham}


# ---------------------------------------------------------------------------------------------- tempering
@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("temperature", [0.3, 2.5])
def test_tempered_grid_density_is_the_power_of_the_density(family, temperature):
    """On the grid, the tempered log probabilities are log_softmax(log p / T) of the untempered values,
    computed densely here from the base family's own grid values."""
    dist = FAMILIES[family]()
    reference = torch.log_softmax(dist.grid_log_density(LEVEL) / temperature, dim=1)  # [B, N]
    tempered = dist.tempered(temperature)
    assert torch.allclose(tempered.log_prob_grid(LEVEL), reference, atol=1e-9)
    # the mode and the order of the rotations stay: the argmax is the same grid point
    assert torch.equal(tempered.grid_logsumexp_and_max(LEVEL)[2], dist.grid_logsumexp_and_max(LEVEL)[2])


def test_family_overrides_stay_in_their_family():
    """The Fourier family scales its coefficients and the matrix Fisher family its matrix (exact), the
    others fall back to the generic grid tempering, whose values equal the overrides'."""
    d = fourier()
    assert type(d.tempered(0.5)) is SO3Distribution
    assert torch.allclose(d.tempered(0.5).coeffs, d.coeffs * 2)
    f = fisher()
    assert type(f.tempered(0.5)) is MatrixFisher and f.tempered(0.5).has_exact_density
    assert isinstance(bingham().tempered(0.5), TemperedDistribution)
    R = haar_rotations(6, seed=4)
    for dist in (d, f):
        generic = TemperedDistribution(dist, 0.5)
        assert torch.allclose(dist.tempered(0.5).log_density(R, LEVEL), generic.log_density(R, LEVEL), atol=1e-9)


def test_tempered_matrix_fisher_is_normalised():
    """The closed-form density of F / T integrates to 1 (volume pi^2): the mean of exp(log density) over
    the equivolumetric level-4 grid, times pi^2, is 1."""
    f = fisher(scale=1.5).tempered(0.7)
    from image2sphere.so3.grid import so3_healpix_grid

    grid = so3_healpix_grid(4).double()  # [N, 3, 3]
    density = f.exact_log_density(grid).exp()  # [B, N]
    assert torch.allclose(density.mean(1) * math.pi**2, torch.ones(3, dtype=torch.float64), atol=2e-3)


@pytest.mark.parametrize("temperature", [0.4, 3.0])
def test_viewpoint_bins_temper_exactly_in_their_family(temperature):
    """The Euler-bin density P_a P_e P_t / V_e raised to 1 / T is again a product of binned factors: the
    family's own tempering keeps its closed form and equals the generic grid tempering on the grid."""
    from image2sphere.distributions.euler_bins import EulerBins

    generator = torch.Generator().manual_seed(2)
    bins = EulerBins(torch.randn(2, 3, 6, generator=generator, dtype=torch.float64))
    tempered = bins.tempered(temperature)
    assert type(tempered) is EulerBins and tempered.has_exact_density
    generic = TemperedDistribution(bins, temperature)
    assert torch.allclose(tempered.log_prob_grid(LEVEL), generic.log_prob_grid(LEVEL), atol=1e-9)
    # the closed form is normalised: its density times pi^2 averages to 1 over the equivolumetric grid
    from image2sphere.so3.grid import so3_healpix_grid

    density = tempered.exact_log_density(so3_healpix_grid(3).double()).exp()
    assert torch.allclose(density.mean(1) * math.pi**2, torch.ones(2, dtype=torch.float64), atol=0.05)


def test_temperatures_compose_and_one_is_the_identity():
    b = bingham()
    assert b.tempered(1.0) is b and b.tempered(1) is b
    twice = b.tempered(0.5).tempered(3.0)
    assert isinstance(twice, TemperedDistribution) and twice.base is b and twice.temperature == pytest.approx(1.5)
    assert torch.allclose(twice.log_prob_grid(LEVEL), b.tempered(1.5).log_prob_grid(LEVEL), atol=1e-12)


@pytest.mark.parametrize("bad", [0, -1.0, math.nan, math.inf, True, "2", None])
def test_bad_temperatures_are_refused(bad):
    with pytest.raises(ValueError, match="temperature"):
        check_temperature(bad)
    with pytest.raises(ValueError, match="temperature"):
        fourier().tempered(bad)


def test_a_point_estimate_is_left_as_it_is():
    p = PointEstimate(haar_rotations(2, seed=1))
    assert p.tempered(0.3) is p


def test_a_stored_recalibration_is_checked():
    good = Recalibration(0.5, 4, "val", 10, 12, 1.0, 1.2, 0.2, 0.01)
    assert Recalibration.from_dict(good.to_dict()) == good
    with pytest.raises(ValueError, match="lacks temperature"):
        Recalibration.from_dict({k: v for k, v in good.to_dict().items() if k != "temperature"}, "x.ckpt")
    with pytest.raises(ValueError, match="x.ckpt.*> 0|> 0.*x.ckpt"):
        Recalibration.from_dict({**good.to_dict(), "temperature": -2.0}, "x.ckpt")


# ---------------------------------------------------------------------------------------------- the fit
def _drawn_at(temperature: float, n: int = 240, seed: int = 0) -> list[ScoredPairs]:
    """Matrix Fisher distributions and one truth per image drawn exactly from the distribution at
    ``temperature``: the temperature that recalibrates the untempered model is ``temperature``."""
    model = fisher(seed=seed, batch=n, scale=2.0)
    generator = torch.Generator().manual_seed(seed + 1)
    truths = model.tempered(temperature).exact_sample(1, generator=generator)  # [n, 1, 3, 3]
    mask = torch.ones(n, 1, dtype=torch.bool)
    return [ScoredPairs(model, truths, mask, tie_break_uniforms(range(n), 1), torch.zeros(n, dtype=torch.long))]


@pytest.mark.parametrize("true_temperature", [0.5, 2.0])
def test_the_fit_recovers_the_temperature_the_data_were_drawn_at(true_temperature, caplog):
    """Maximum likelihood over 240 images recovers the temperature the truths were drawn at (to 20 %),
    the log likelihood rises and the calibration error falls to that of a calibrated model."""
    batches = _drawn_at(true_temperature)
    with caplog.at_level("WARNING", logger="image2sphere.recalibration"):
        fit = fit_temperature(batches, level=3)
    assert not fit.degenerate and not caplog.records  # inside the bounds: no warning
    assert fit.temperature == pytest.approx(true_temperature, rel=0.2)
    assert fit.log_likelihood_after > fit.log_likelihood_before
    assert fit.ece_before > 0.1 and fit.ece_after < 0.06
    assert (fit.n_images, fit.n_pairs, fit.grid_level, fit.split) == (240, 240, 3, "val")
    # the reported numbers are those of the data at the fitted temperature
    ll, ece, n = score_temperature(batches, fit.temperature, 3, num_classes=1)
    assert (ll, ece, n) == (pytest.approx(fit.log_likelihood_after), pytest.approx(fit.ece_after), 240)


def test_a_calibrated_model_keeps_a_temperature_near_one():
    fit = fit_temperature(_drawn_at(1.0, seed=3), level=3)
    assert fit.temperature == pytest.approx(1.0, rel=0.2)
    assert fit.log_likelihood_after >= fit.log_likelihood_before


def test_every_class_weighs_the_same_and_each_gets_its_own_diagnostic_temperature():
    """Two classes drawn at temperatures 0.5 and 2, the second with far fewer images: the fitted
    temperature lies between them (the classes weigh the same, not their pairs), and the per-class
    diagnostic recovers each class's own temperature."""
    sharp, broad = _drawn_at(0.5, n=240, seed=0)[0], _drawn_at(2.0, n=80, seed=5)[0]
    batches = [sharp, broad._replace(class_index=torch.ones(80, dtype=torch.long))]
    fit = fit_temperature(batches, level=3)
    assert fit.class_temperatures[0] == pytest.approx(0.5, rel=0.2)
    assert fit.class_temperatures[1] == pytest.approx(2.0, rel=0.25)
    assert 0.6 < fit.temperature < 1.7
    assert "each class alone" in fit.describe()
    # a pooled mean over pairs would follow the 240-image class much more closely
    pooled = fit_temperature([sharp, broad], level=3)
    assert pooled.temperature < fit.temperature


def test_an_image_weighs_the_same_whatever_the_size_of_its_set_as_in_the_tests_log_likelihood():
    """One class of 80 images drawn at temperature 0.5 with one rotation each and 80 drawn at 2 whose
    set holds their rotation 8 times: each image's mean over its set is that of its one rotation, so the
    fit, its log likelihood and the test's headline are those of the same images with sets of one. A
    mean over all pairs would let the 640 pairs of the broad images pull the temperature towards 2."""
    sharp, broad = _drawn_at(0.5, n=80, seed=0)[0], _drawn_at(2.0, n=80, seed=5)[0]
    repeated = broad._replace(targets=broad.targets.expand(80, 8, 3, 3), mask=torch.ones(80, 8, dtype=torch.bool),
                              u=tie_break_uniforms(range(80, 160), 8))  # fmt: skip
    single = fit_temperature([sharp, broad], level=3)
    fit = fit_temperature([sharp, repeated], level=3)
    assert fit.temperature == pytest.approx(single.temperature, rel=0.02)
    assert fit.log_likelihood_before == pytest.approx(single.log_likelihood_before, rel=1e-6)
    assert fit.n_pairs == 80 + 640 and single.n_pairs == 160
    before, _, _ = score_temperature([sharp, repeated], 1.0, 3, 1)
    assert before == pytest.approx(single.log_likelihood_before, rel=1e-6)


def _pairs(model, truths: torch.Tensor) -> list[ScoredPairs]:
    n = len(truths)
    mask = torch.ones(n, 1, dtype=torch.bool)
    return [
        ScoredPairs(model, truths[:, None], mask, tie_break_uniforms(range(n), 1), torch.zeros(n, dtype=torch.long))
    ]


@pytest.mark.parametrize("bound", ["upper", "lower"])
def test_a_fit_at_a_search_bound_is_degenerate_and_keeps_temperature_one(bound, caplog):
    """Truths drawn independently of sharp distributions: flattening them towards uniform scores best, so the
    search runs to the upper bound 50; truths exactly at the grid mode: sharpening scores best without limit
    (the lower bound 1/50). Either way the fit warns, saying what the bound means, and keeps T = 1 (the
    model's own figures before and after), recording the bound it reached."""
    model = fisher(seed=2, batch=24, scale=4.0)
    truths = haar_rotations(24, seed=7) if bound == "upper" else model.mode(LEVEL)
    with caplog.at_level("WARNING", logger="image2sphere.recalibration"):
        fit = fit_temperature(_pairs(model, truths), level=LEVEL)
    assert fit.degenerate and fit.temperature == 1.0
    assert fit.degenerate_temperature == pytest.approx(50.0 if bound == "upper" else 0.02, rel=0.03)
    assert (fit.log_likelihood_after, fit.ece_after) == (fit.log_likelihood_before, fit.ece_before)
    (warning,) = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert "Recalibration is degenerate" in warning and "T = 1 is kept" in warning
    meaning = "carries no information on the val split" if bound == "upper" else "sharpened without limit"
    assert meaning in warning and f"{bound} bound" in warning
    assert fit.describe().startswith("no temperature (T = 1 kept)") and "degenerate" in fit.describe()
    # stored and read back as such; a record written before the field existed reads as not degenerate
    assert Recalibration.from_dict(fit.to_dict()) == fit
    old = {k: v for k, v in fit.to_dict().items() if k != "degenerate_temperature"}
    assert not Recalibration.from_dict(old).degenerate


def test_same_temperature_allows_the_search_tolerance_only():
    fit = Recalibration(0.5, 4, "val", 10, 12, 1.0, 1.2, 0.2, 0.01)
    assert fit.same_temperature(fit) and fit.same_temperature(dataclasses.replace(fit, temperature=0.505))
    assert not fit.same_temperature(dataclasses.replace(fit, temperature=0.55)) and not fit.same_temperature(None)
    degenerate = dataclasses.replace(fit, temperature=1.0, degenerate_temperature=49.8)
    assert degenerate.same_temperature(dataclasses.replace(degenerate, degenerate_temperature=0.02))
    assert not degenerate.same_temperature(dataclasses.replace(fit, temperature=1.0))


def test_the_fit_sums_over_processes_with_reduce():
    """``reduce`` sees the pooled sums of this process; doubling them (two processes with the same share)
    changes nothing in the means, so the same temperature comes out."""
    batches = _drawn_at(0.5)
    seen = []

    def twice(totals):
        seen.append(totals.clone())
        return 2 * totals

    assert fit_temperature(batches, 3, reduce=twice).temperature == pytest.approx(
        fit_temperature(batches, 3).temperature
    )
    assert seen and all(t[..., 1].sum() == 240 for t in seen)


# ---------------------------------------------------------------------------------------------- whole runs
def test_the_training_run_fits_stores_and_reports_the_recalibration(tiny_run):
    """The tiny run (recalibration=fit, the default) stored its temperature in last.ckpt and reported the
    log likelihood and ECE before and after, per class and averaged."""
    ckpt = torch.load(tiny_run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    fit = Recalibration.from_dict(ckpt["recalibration"])
    metrics = read_metrics(tiny_run)
    assert metrics["temperature"] == pytest.approx(fit.temperature)
    for key in ("log_likelihood_calibrated", "calibration_ece_calibrated", "hdr_coverage_50_calibrated"):
        assert key in metrics and all(f"{key}/{c}" in metrics for c in ("cube", "cone"))
    # the accuracies are the model's own: the recalibration changes no ranking
    assert "acc15_calibrated" not in metrics


@pytest.mark.slow
def test_eval_applies_fits_and_turns_off_the_recalibration(tiny_run, tmp_path, monkeypatch):
    """src.eval: auto reports the stored temperature's metrics; off reports none; fit on a checkpoint without
    a temperature writes a new checkpoint beside it (never replacing one), whose temperature the next eval
    uses; fit on a checkpoint that has one says so and writes nothing when the refit gives the same."""
    import shutil

    import image2sphere.training.module as module_code

    ckpt = tmp_path / "last.ckpt"
    shutil.copy(tiny_run / "checkpoints" / "last.ckpt", ckpt)
    base = ["eval_grid_level=3", "plots=0", "logger=none", "trainer.accelerator=cpu"]

    def run_eval(path, *args, check=True):
        out = tmp_path / f"eval{len(list(tmp_path.glob('eval*')))}"
        proc = run_module([sys.executable, "-m", "src.eval", *base, f"ckpt_path={path}", *args,
                           f"hydra.run.dir={out}"], check=check)  # fmt: skip
        metrics = out / "metrics.json"
        return proc, json.loads(metrics.read_text()) if metrics.is_file() else None

    (_, auto), (_, off) = run_eval(ckpt), run_eval(ckpt, "recalibration=off")
    assert "log_likelihood_calibrated" in auto and "log_likelihood_calibrated" not in off
    assert auto["log_likelihood"] == pytest.approx(off["log_likelihood"])  # the model's own, both times

    # the tiny run's own fit may be degenerate (T = 1, nothing written): a fit of T = 0.5 stands in for it
    real_fit = module_code.fit_temperature
    fit_half = lambda *a, **k: dataclasses.replace(real_fit(*a, **k), temperature=0.5, degenerate_temperature=None)  # noqa: E731
    monkeypatch.setattr(module_code, "fit_temperature", fit_half)
    bare = tmp_path / "bare.ckpt"  # the checkpoint without its temperature
    torch.save({k: v for k, v in torch.load(ckpt, weights_only=True).items() if k != "recalibration"}, bare)
    original = bare.read_bytes()
    _, fitted = run_eval(bare, "recalibration=fit")
    target = tmp_path / "bare.recalibrated.ckpt"
    assert target.is_file() and bare.read_bytes() == original
    stored = torch.load(target, map_location="cpu", weights_only=True)["recalibration"]
    assert fitted["temperature"] == stored["temperature"] == 0.5
    again, _ = run_eval(bare, "recalibration=fit", check=False)
    assert again.returncode != 0 and "already exists" in again.stderr + again.stdout
    # fit on the checkpoint that has the temperature: it says so, the same temperature comes out, no copy
    proc, refitted = run_eval(target, "recalibration=fit")
    out = proc.stdout + proc.stderr
    assert "already holds a recalibration" in out and "nothing written: the fit gives the temperature" in out
    assert refitted["temperature"] == 0.5 and not (tmp_path / "bare.recalibrated.recalibrated.ckpt").exists()
    # the same without a stand-in: the tiny run's own checkpoint refitted on its own split (degenerate or not)
    monkeypatch.setattr(module_code, "fit_temperature", real_fit)
    proc, refitted = run_eval(ckpt, "recalibration=fit")
    assert (
        "already holds a recalibration" in proc.stdout + proc.stderr and "nothing written" in proc.stdout + proc.stderr
    )
    assert refitted["temperature"] == pytest.approx(auto["temperature"], rel=0.03)
    assert not (tmp_path / "last.recalibrated.ckpt").exists()


def test_the_reliability_diagram_draws_the_recalibrated_curve(tiny_run):
    """The tiny run's metrics have both calibrations: the diagram has the mean before and after, the
    latter labelled with its temperature and ECE; without the recalibrated keys there is no such line."""
    from image2sphere.plot import plot_reliability

    metrics = read_metrics(tiny_run)
    labels = [line.get_label() for line in plot_reliability(metrics).axes[0].get_lines()]
    after = [label for label in labels if "recalibrated" in label]
    assert len(after) == 1 and f"{metrics['calibration_ece_calibrated']:.3f}" in after[0]
    plain = {k: v for k, v in metrics.items() if "calibrated" not in k}
    assert not any("recalibrated" in line.get_label() for line in plot_reliability(plain).axes[0].get_lines())


def test_a_run_without_a_validation_split_trains_tests_and_fits_nothing(tmp_path):
    """dataset.val_per_shape=0 (the paper's SYMSOL protocol has no validation split): the run ends as
    before, says why no temperature was fitted, and its checkpoint and metrics have none."""
    run = tmp_path / "run"
    proc = run_train(["trainer.max_epochs=1", "dataset.val_per_shape=0", "logger=none", f"hydra.run.dir={run}"],
                     tmp_path / "data", tmp_path / "logs")  # fmt: skip
    assert "no validation split; no temperature fitted" in proc.stdout + proc.stderr
    assert "recalibration" not in torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    metrics = read_metrics(run)
    assert "log_likelihood" in metrics and "temperature" not in metrics and "log_likelihood_calibrated" not in metrics


@pytest.mark.slow  # a training run: about 3 to 5 s
def test_a_degenerate_fit_after_training_keeps_temperature_one_and_says_so(tmp_path, monkeypatch):
    """src.train's fit after training goes through the same rule: here the search is confined to [0.99, 1.01],
    so it ends at a bound. The run warns, stores T = 1 with the bound it reached, and its recalibrated figures
    are the model's own."""
    import functools

    import image2sphere.training.module as module_code

    monkeypatch.setattr(module_code, "fit_temperature", functools.partial(fit_temperature, bounds=(0.99, 1.01)))
    run = tmp_path / "run"
    proc = run_train(["trainer.max_epochs=1", "logger=none", f"hydra.run.dir={run}"], tmp_path / "data",
                     tmp_path / "logs")  # fmt: skip
    out = proc.stdout + proc.stderr
    assert "Recalibration is degenerate: the fitted temperature" in out and "T = 1 is kept" in out
    assert "Recalibration: no temperature (T = 1 kept)" in out
    stored = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)["recalibration"]
    assert stored["temperature"] == 1.0 and stored["degenerate_temperature"] == pytest.approx(1.0, abs=0.011)
    metrics = read_metrics(run)
    assert metrics["temperature"] == 1.0
    assert metrics["log_likelihood_calibrated"] == pytest.approx(metrics["log_likelihood"])
    assert metrics["calibration_ece_calibrated"] == pytest.approx(metrics["calibration_ece"])


@pytest.mark.slow
def test_testing_a_stored_checkpoint_reports_its_recalibration(tiny_run, tmp_path):
    """``train=false ckpt_path=...``: the test of a loaded checkpoint reports its stored temperature's
    metrics, equal to those the training run reported."""
    run = tmp_path / "run"
    ckpt = tiny_run / "checkpoints" / "last.ckpt"
    run_train(["train=false", f"ckpt_path={ckpt}", "logger=none", f"hydra.run.dir={run}"], tmp_path / "data",
              tmp_path / "logs")  # fmt: skip
    metrics, original = read_metrics(run), read_metrics(tiny_run)
    assert metrics["temperature"] == pytest.approx(original["temperature"])
    assert metrics["log_likelihood_calibrated"] == pytest.approx(original["log_likelihood_calibrated"], rel=1e-5)
