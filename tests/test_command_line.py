"""A mistyped key or group option on the command line (:mod:`image2sphere.training.command_line`): one line that
names the closest existing names, before Hydra composes, for ``src.train``, ``src.eval`` and ``src.predict``;
genuinely new keys, sweeps and Hydra's own flags go through as before."""

from __future__ import annotations

import sys

import pytest

from conftest import ENV, run_module
from image2sphere.training import command_line
from image2sphere.training.command_line import command_line_problem

LMAX = "lmx is not a config key; did you mean lmax?"


@pytest.mark.parametrize(
    ("config", "argv", "line"),
    [
        ("train.yaml", ["model=wigner"], "model=wigner is not an option of model; closest: wigner_regression "
         "(all options: python -m src.train --help)"),
        ("train.yaml", ["dataset=pascal3D"], "dataset=pascal3D is not an option of dataset; closest: pascal3d "
         "(all options: python -m src.train --help)"),
        ("train.yaml", ["-m", "model=i2s,wigner"], "model=wigner is not an option of model; closest: "
         "wigner_regression (all options: python -m src.train --help)"),
        ("train.yaml", ["experiment=fidelity/aftr"], "experiment=fidelity/aftr is not an option of experiment; "
         "closest: fidelity/after, fidelity/before, fidelity/init (all options: python -m src.train --help)"),
        ("train.yaml", ["hydra/launcher=slurmm"], "hydra/launcher=slurmm is not an option of hydra/launcher; "
         "closest: slurm (all options: python -m src.train --help)"),
        ("train.yaml", ["hydra/launchr=slurm"], "hydra/launchr is not a config group; did you mean "
         "hydra/launcher? (the groups: python -m src.train --help)"),
        ("eval.yaml", ["ckpt_path=x", "model=rotation_flow"], "model=rotation_flow: python -m src.eval uses the "
         "network its checkpoint holds (ckpt_path=...), whatever model that is; drop model=rotation_flow (to train "
         "with it: python -m src.train model=rotation_flow)"),
        ("eval.yaml", ["ckpt_path=x", "dataset=symsol"], "dataset=symsol is not an option of dataset; closest: "
         "symsol1, symsol2, symsol_rendered (all options: python -m src.eval --help)"),
    ],
    ids=["option", "case", "sweep", "subfolder", "hydra group", "group path", "eval model", "eval dataset"],
)  # fmt: skip
def test_an_unknown_group_option_names_the_closest_without_composing(config, argv, line, monkeypatch):
    monkeypatch.setattr(command_line, "_compose", lambda *a: pytest.fail("composed for a group option"))
    assert command_line_problem(config, argv) == line


@pytest.mark.parametrize(
    ("config", "argv", "line"),
    [
        ("train.yaml", ["lmx=4"], LMAX),
        ("train.yaml", ["+lmx=4"], LMAX),  # Hydra's own advice for lmx=4, which trained with lmax 6
        ("train.yaml", ["-m", "lmx=2,4", "seed=0,1"], LMAX),
        ("train.yaml", ["trainer.max_epoch=3"], "trainer.max_epoch is not a config key; did you mean "
         "trainer.max_epochs or trainer.min_epochs?"),
        ("train.yaml", ["model=ipdf", "model.net.sphere_channels=16"], "model.net.sphere_channels is not a config "
         "key of python -m src.train (every key: python -m src.train --cfg job)"),
        ("predict.yaml", ["ckpt_path=x", "image=y", "levl=3"], "levl is not a config key; did you mean level?"),
        ("predict.yaml", ["ckpt_path=x", "image=y", "dataset=symsol1"], "dataset=symsol1: dataset is not a config "
         "group of python -m src.predict (its groups: paths)"),
    ],
    ids=["key", "added key", "multirun", "nested", "key of another model", "predict", "predict group"],
)  # fmt: skip
def test_an_unknown_key_names_the_closest_keys_at_its_level(config, argv, line):
    assert command_line_problem(config, argv) == line


@pytest.mark.parametrize(
    "argv",
    [
        ["+trainer.profiler=simple"],  # a new key with no existing key that close: Hydra adds it
        ["+model.foo=1", "experiment=fidelity/after"],
        ["-m", "model=i2s,ipdf", "seed=0,1", "trainer.fast_dev_run=true"],
        ["--help", "lmx=4"],  # Hydra's flags that print and exit: not checked
        ["--cfg", "job", "hydra/launcher=slurm", "hydra.run.dir=x"],
    ],
    ids=["new key", "new key of a model", "sweep", "help", "hydra"],
)
def test_existing_and_genuinely_new_keys_go_through(argv):
    assert command_line_problem("train.yaml", argv) is None


def test_options_of_the_configs_own_groups_compose_nothing(monkeypatch):
    monkeypatch.setattr(command_line, "_compose", lambda *a: pytest.fail("composed for group options"))
    assert command_line_problem("train.yaml", ["model=ipdf", "dataset=symsol1", "experiment=symsol1"]) is None
    assert command_line_problem("train.yaml", []) is None


def test_keys_are_judged_on_the_config_of_the_groups_composed_once_per_process(monkeypatch):
    """Key overrides are checked on the config of the group overrides alone, composed once for every command
    line with the same groups; only a key that config lacks is judged on the whole command line's config."""
    composed, real = [], command_line._compose

    def compose(loader, name, overrides):
        composed.append(list(overrides))
        return real(loader, name, overrides)

    monkeypatch.setattr(command_line, "_compose", compose)
    monkeypatch.setattr(command_line, "_GROUP_CONFIGS", {})
    for seed in range(3):
        argv = ["model=ipdf", f"seed={seed}", "trainer.max_epochs=2", f"hydra.run.dir=runs/{seed}", "+my_note=1"]
        assert command_line_problem("train.yaml", argv) is None
    assert composed == [["model=ipdf"]]
    assert command_line_problem("train.yaml", ["model=ipdf", "+lmx=3"]) == LMAX  # the kept config, as above
    assert composed == [["model=ipdf"]]
    line = (
        "model.net.sphere_channels is not a config key of python -m src.train (every key: python -m src.train "
        "--cfg job)"
    )
    assert command_line_problem("train.yaml", ["model=ipdf", "model.net.sphere_channels=16"]) == line
    assert composed[1:] == [["model=ipdf", "model.net.sphere_channels=16"]]  # a key the groups' config lacks
    assert command_line_problem("train.yaml", ["model=i2s", "seed=1"]) is None
    assert composed[-1] == ["model=i2s"]  # other groups: their own config


def test_the_entry_point_prints_one_line_and_writes_nothing_and_hydra_full_error_keeps_hydras_report(tmp_path):
    """In-process runs of the real entry points: exit status 1, one line on stderr, no log directory made (the
    check comes before Hydra makes the run's directory); a multirun launches no job."""
    logs = tmp_path / "logs"
    train = run_module([sys.executable, "-m", "src.train", "-m", "lmx=2,4", f"paths.log_dir={logs}"], check=False)
    assert (train.returncode, train.stderr.splitlines()) == (1, [f"Error: {LMAX}"]), train.stderr
    predict = run_module([sys.executable, "-m", "src.predict", "ckpt_path=x", "image=y", "model=ipdf",
                          f"paths.log_dir={logs}"], check=False)  # fmt: skip
    assert predict.returncode == 1 and predict.stderr.startswith("Error: model=ipdf: python -m src.predict uses")
    assert len(predict.stderr.splitlines()) == 1
    assert not logs.exists()
    hydra = run_module([sys.executable, "-m", "src.train", "lmx=4", f"paths.log_dir={logs}"],
                       env={**ENV, "HYDRA_FULL_ERROR": "1"}, check=False)  # fmt: skip
    assert hydra.returncode == 1 and "Could not override 'lmx'" in hydra.stderr and "Error: lmx" not in hydra.stderr
