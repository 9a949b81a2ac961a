"""The Lightning internals the project relies on still exist with the shape it uses.

The run's signal handling and checkpointing (src/image2sphere/training/) reach into private parts of
Lightning, which any release may change without notice; pyproject.toml therefore bounds Lightning below
the next minor release (``lightning>=2.5,<2.7``). Each check here names the internal, the project file
that relies on it, and that the upper bound must stay until that file is ported: a failure after raising
the bound says what to port. Quick tier (one bare ``Trainer``, no fitting).
"""

from __future__ import annotations

import inspect
from pathlib import Path

import lightning
import lightning.pytorch as pl
import pytest
from lightning.pytorch.callbacks import ModelCheckpoint
from packaging.requirements import Requirement
from packaging.version import Version

REPO = Path(__file__).resolve().parents[1]
BOUND = "lightning<2.7"
STOP = "src/image2sphere/training/stop.py"
CHECKPOINT = "src/image2sphere/training/checkpoint.py"
PIPELINE = "src/image2sphere/training/pipeline.py"
ENTRY = "src/image2sphere/training/entry.py"


def changed(internal: str, user: str, how: str) -> str:
    """The failure message: which internal changed, how, who relies on it, and what to keep."""
    return (
        f"Lightning internal {internal} changed ({how}); {user} relies on it. Keep pyproject.toml's upper "
        f"bound ({BOUND}) until {user} is ported to this Lightning version."
    )


def parameters(function) -> list[str]:
    """The parameter names of ``function`` (``self`` included for a function defined in a class)."""
    return list(inspect.signature(function).parameters)


def test_pyproject_bounds_lightning_above_and_the_installed_release_is_inside():
    """The checks below are of the installed Lightning only: pyproject.toml must keep every other release
    out until they pass with it."""
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    dependencies = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    requirement = next((r for r in map(Requirement, dependencies) if r.name.lower() == "lightning"), None)
    assert requirement is not None, "pyproject.toml no longer names lightning"
    assert any(spec.operator == "<" for spec in requirement.specifier), (
        f"pyproject.toml asks for {requirement}: the project relies on Lightning internals (this module), so "
        f"keep an upper bound ({BOUND}) until src/image2sphere/training/ is ported to a newer release"
    )
    installed = Version(lightning.__version__)
    assert requirement.specifier.contains(installed), f"installed Lightning {installed} is outside {requirement}"


@pytest.fixture(scope="module")
def trainer() -> pl.Trainer:
    return pl.Trainer(
        accelerator="cpu",
        devices=1,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )


def test_signal_connector():
    """stop.py subclasses ``_SignalConnector`` (``FlagOnlySignalConnector``): built from the trainer, with
    ``register_signal_handlers()`` and ``teardown()`` overridden and ``received_sigterm`` and
    ``_original_handlers`` set by them."""
    internal = "lightning.pytorch.trainer.connectors.signal_connector._SignalConnector"
    try:
        from lightning.pytorch.trainer.connectors.signal_connector import _SignalConnector
    except ImportError as e:
        pytest.fail(changed(internal, STOP, f"it no longer imports: {e}"))
    assert parameters(_SignalConnector.__init__) == ["self", "trainer"], changed(
        internal, STOP, f"__init__{inspect.signature(_SignalConnector.__init__)} instead of (self, trainer)"
    )
    for method in ("register_signal_handlers", "teardown"):
        assert callable(getattr(_SignalConnector, method, None)), changed(internal, STOP, f"no method {method}")
        assert parameters(getattr(_SignalConnector, method)) == ["self"], changed(
            internal, STOP, f"{method} takes {parameters(getattr(_SignalConnector, method))}, not only self"
        )
    connector = _SignalConnector(None)
    for attribute in ("received_sigterm", "_original_handlers"):
        assert hasattr(connector, attribute), changed(internal, STOP, f"its instances have no {attribute}")


def test_trainer_signal_connector(trainer):
    """stop.py replaces ``Trainer._signal_connector`` before fitting, and relies on the trainer calling its
    ``register_signal_handlers()`` when a run starts and its ``teardown()`` when it ends, and on
    ``Trainer.received_sigterm`` being the connector's flag."""
    from lightning.pytorch.trainer.connectors.signal_connector import _SignalConnector

    internal = "Trainer._signal_connector"
    assert isinstance(getattr(trainer, "_signal_connector", None), _SignalConnector), changed(
        internal, STOP, f"a Trainer's _signal_connector is {type(getattr(trainer, '_signal_connector', None))}"
    )
    source = inspect.getsource(pl.Trainer)
    for call in ("self._signal_connector.register_signal_handlers()", "self._signal_connector.teardown()"):
        assert call in source, changed(internal, STOP, f"Trainer no longer calls {call}")
    connector = trainer._signal_connector
    connector.received_sigterm = True
    try:
        assert trainer.received_sigterm is True, changed(
            internal, STOP, "Trainer.received_sigterm no longer reads _signal_connector.received_sigterm"
        )
    finally:
        connector.received_sigterm = False


def test_trainer_accelerator_connector(trainer):
    """stop.py (``requeue_job``) and pipeline.py (``_no_other_rank_yet``) read the cluster environment
    through ``Trainer._accelerator_connector.cluster_environment``, and its ``creates_processes_externally``."""
    from lightning.fabric.plugins.environments import ClusterEnvironment

    internal = "Trainer._accelerator_connector.cluster_environment"
    environment = getattr(getattr(trainer, "_accelerator_connector", None), "cluster_environment", None)
    assert isinstance(environment, ClusterEnvironment), changed(
        internal, f"{STOP} and {PIPELINE}", f"it is {type(environment)}, not a ClusterEnvironment"
    )
    assert isinstance(environment.creates_processes_externally, bool), changed(
        internal, PIPELINE, "its creates_processes_externally is not a bool"
    )


def test_model_checkpoint_last_checkpoint():
    """checkpoint.py (``EpochCheckpoint``) writes ``last.ckpt`` itself by
    ``self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))``, skips a step already saved
    by ``_last_global_step_saved`` and returns ``last_model_path``."""
    for method, expected in (
        ("_save_last_checkpoint", ["self", "trainer", "monitor_candidates"]),
        ("_monitor_candidates", ["self", "trainer"]),
    ):
        internal = f"ModelCheckpoint.{method}"
        assert callable(getattr(ModelCheckpoint, method, None)), changed(internal, CHECKPOINT, "no such method")
        got = parameters(getattr(ModelCheckpoint, method))
        assert got == expected, changed(internal, CHECKPOINT, f"it takes {got}, not {expected}")
    callback = ModelCheckpoint(save_last=True)
    assert callback._last_global_step_saved == 0, changed(
        "ModelCheckpoint._last_global_step_saved", CHECKPOINT, "a new callback does not start it at step 0"
    )
    assert callback.last_model_path == "", changed(
        "ModelCheckpoint.last_model_path", CHECKPOINT, "a new callback does not start it empty"
    )


def test_local_file_protocol():
    """checkpoint.py (``AtomicCheckpointIO``) writes local paths itself and hands the others to Lightning,
    telling them apart with ``_is_local_file_protocol``."""
    internal = "lightning.fabric.utilities.cloud_io._is_local_file_protocol"
    try:
        from lightning.fabric.utilities.cloud_io import _is_local_file_protocol
    except ImportError as e:
        pytest.fail(changed(internal, CHECKPOINT, f"it no longer imports: {e}"))
    assert _is_local_file_protocol("/tmp/run/last.ckpt") and _is_local_file_protocol("run/last.ckpt"), changed(
        internal, CHECKPOINT, "a local path is not local"
    )
    assert not _is_local_file_protocol("s3://bucket/last.ckpt"), changed(internal, CHECKPOINT, "s3:// is local")


def test_fit_loop_progress(trainer):
    """stop.py reads ``trainer.fit_loop.epoch_loop.batch_progress.is_last_batch``; checkpoint.py reads a
    checkpoint's ``loops.fit_loop`` entries ``epoch_loop.batch_progress`` (``current.processed``,
    ``is_last_batch``) and ``epoch_progress`` (``current.processed``) to resume within an epoch; entry.py
    tells a loop's error by its module under ``lightning.pytorch.loops``."""
    internal = "Trainer.fit_loop.epoch_loop.batch_progress"
    progress = trainer.fit_loop.epoch_loop.batch_progress
    assert isinstance(progress.is_last_batch, bool), changed(internal, STOP, "it has no bool is_last_batch")
    state = trainer.fit_loop.state_dict()
    internal = "the fit loop's state_dict (a checkpoint's loops.fit_loop)"
    batch = state.get("epoch_loop.batch_progress", {})
    assert "is_last_batch" in batch and "processed" in batch.get("current", {}), changed(
        internal, CHECKPOINT, f"epoch_loop.batch_progress is {batch}"
    )
    assert "processed" in state.get("epoch_progress", {}).get("current", {}), changed(
        internal, CHECKPOINT, f"epoch_progress is {state.get('epoch_progress')}"
    )
    for loop in (trainer.fit_loop, trainer.fit_loop.epoch_loop):
        module = type(loop).__module__
        assert module.startswith("lightning.pytorch.loops."), changed(
            "the module of Lightning's loops", ENTRY, f"{type(loop).__name__} is defined in {module}"
        )
