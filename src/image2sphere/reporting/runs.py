"""Finished and unfinished runs under the directories a user names, and what each run was.

A run directory is one Hydra job's output directory: it holds ``.hydra/config.yaml``,
``.hydra/hydra.yaml`` and ``.hydra/overrides.yaml`` from the start, and ``metrics.json`` once its
test has finished (``src.train`` writes it last). A directory with ``.hydra/`` but no readable
``metrics.json`` is an *unfinished* run (still running, failed, stopped, or killed): it is reported,
never skipped in silence.

What a run was is looked up by key: a config group's choice (``model``, ``dataset``, ``experiment``,
``table``...: ``hydra.runtime.choices`` of ``.hydra/hydra.yaml``) or a dotted key of the composed
config (``lmax``, ``seed``, ``model.net.num_components``, ``dataset.shape``).

**A resumed run** (``python -m src.train ckpt_path=<run>/checkpoints/last.ckpt ...``) trains what its
checkpoint's stored config says, not what its own command line composes, and writes the config it really
used to ``resumed_config.yaml``. Such a run is read as what it really was:

* its config is ``resumed_config.yaml`` (not ``.hydra/config.yaml``);
* its group choices are those of the run that wrote the checkpoint (``.hydra/hydra.yaml`` of the run
  directory the checkpoint lies in, followed back through a resume of a resume), except the groups that
  decide where and how a run goes (:data:`OWN_GROUPS`: trainer, logger, callbacks, paths, debug, Hydra's
  own) and any group the resume's command line names, which are the resumed run's own;
* its overrides are the original run's, plus those of the resume's command line that changed a value
  (``trainer.max_epochs=60`` on a run of 40 epochs), each replacing the original's of the same key;
  ``ckpt_path`` itself is none (it says where the run started from, not what it trained).

When the original run's directory is no longer beside the checkpoint (the checkpoint was copied
elsewhere), its choices cannot be known: the other groups' choices are null (unknown, not the defaults the
resume's command line composed), a note (:attr:`Run.notes`) says so, and its config values still come
from ``resumed_config.yaml``.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from omegaconf import DictConfig, OmegaConf

from image2sphere.config_text import config_value, override_key
from image2sphere.loop_progress import batches_done_in_epoch, epoch_resumed_in, has_loop_state

__all__ = [
    "LAST_CHECKPOINT",
    "OWN_GROUPS",
    "RESUMED_CONFIG",
    "Run",
    "UnfinishedRun",
    "counted_runs",
    "find_runs",
    "incomplete_reason",
    "values_equal",
]

_MISSING = object()
# the config a resumed run really used (written by src.train beside .hydra/)
RESUMED_CONFIG = "resumed_config.yaml"
# groups whose choice a resumed run takes from its own command line, as its config does: where and how it
# runs (and every group of Hydra's own, hydra/...); any other group's choice is the original run's
OWN_GROUPS = ("trainer", "logger", "callbacks", "paths", "debug", "hydra")
# where a run's checkpoint of its last epoch lies, relative to the run directory (conf/callbacks/model_checkpoint.yaml)
LAST_CHECKPOINT = Path("checkpoints") / "last.ckpt"
# how far a resume of a resume of ... is followed back
_MAX_RESUMES = 50


@dataclass
class Run:
    """One finished run: its directory, metrics, group choices, config and command-line overrides."""

    path: Path
    metrics: dict[str, float]
    choices: dict[str, Any]
    config: dict[str, Any]
    overrides: list[str] = field(default_factory=list)
    # the ``hydra`` section of ``.hydra/hydra.yaml`` (mode, sweeper, job number ...); empty without the file
    hydra: dict[str, Any] = field(default_factory=dict)
    # a resumed run: the checkpoint it started from (its ckpt_path, absolute); None for a run from scratch
    resumed_from: Path | None = None
    # what a reader of a table should know about how this run was read (e.g. choices that are unknown)
    notes: list[str] = field(default_factory=list)
    # why the run, although it has metrics, did not train and test as configured (``fast_dev_run``,
    # ``unfinished: stopped after epoch 3 of 40``...; :func:`incomplete_reason`); None for a finished run
    incomplete: str | None = None
    # the config as OmegaConf's, made on the first lookup
    _node: DictConfig | None = field(default=None, init=False, repr=False, compare=False)

    def get(self, key: str, default: Any = _MISSING) -> Any:
        """A group's choice (``model``) or a dotted config value (``model.net.lmax``, interpolations resolved);
        ``default`` (or ``KeyError``) when the run has neither."""
        if key in self.choices:
            return self.choices[key]
        if self._node is None:
            self._node = OmegaConf.create(self.config)
        value = config_value(self._node, key, _MISSING)
        if value is _MISSING:
            if default is _MISSING:
                raise KeyError(key)
            return default
        return value

    def matches(self, match: dict[str, Any]) -> bool:
        """Whether every ``key: value`` of ``match`` holds for this run (a key it lacks is ``null``)."""
        return all(values_equal(self.get(k, None), v) for k, v in match.items())

    @property
    def seed(self) -> Any:
        return self.get("seed", None)

    @property
    def multirun_job(self) -> bool:
        """A job of a Hydra multirun (``python -m src.train -m ...``, a paper table, an Optuna study)."""
        return str(self.hydra.get("mode", "")).upper() == "MULTIRUN"

    @property
    def smoke_test(self) -> bool:
        """A ``trainer.fast_dev_run`` run: its metrics come from one batch."""
        return bool(self.get("trainer.fast_dev_run", False))


@dataclass
class UnfinishedRun:
    path: Path
    reason: str


def values_equal(actual: Any, expected: Any) -> bool:
    """``actual`` (from a run) equals ``expected`` (from a table layout): ``null`` only equals ``null``;
    numbers compare as numbers, anything else as its text (``"2"`` from a command line equals ``2``)."""
    if expected is None or actual is None:
        return expected is None and actual is None
    if isinstance(expected, bool) or isinstance(actual, bool):
        return str(actual).lower() == str(expected).lower()
    try:
        return math.isclose(float(actual), float(expected), rel_tol=0, abs_tol=1e-12)
    except (TypeError, ValueError):
        return str(actual) == str(expected)


def _read_yaml(path: Path) -> Any:
    # Hydra's files hold interpolations (${...}) as text: plain YAML reading keeps them as strings
    with open(path, encoding="utf-8") as f:
        return yaml.safe_load(f)


def _read_metrics(path: Path) -> tuple[dict[str, float] | None, str]:
    if not path.is_file():
        return None, "no metrics.json (still running, failed, or stopped before its test)"
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except (OSError, ValueError) as e:
        return None, f"metrics.json is not readable JSON ({e})"
    if not isinstance(data, dict) or not data:
        return None, "metrics.json holds no metrics"
    metrics = {}
    for k, v in data.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            return None, f"metrics.json: {k!r} is not a number ({v!r})"
        metrics[str(k)] = float(v)
    return metrics, ""


@dataclass
class _Setting:
    """What a run directory says the run was (its effective config, choices and overrides)."""

    config: dict[str, Any]
    choices: dict[str, Any]
    overrides: list[str]
    hydra: dict[str, Any]
    resumed_from: Path | None = None
    notes: list[str] = field(default_factory=list)


def _own_group(group: str) -> bool:
    return any(group == g or group.startswith(g + "/") for g in OWN_GROUPS)


def _checkpoint_run_dir(ckpt: Path) -> Path | None:
    """The run directory a checkpoint lies in: the nearest folder above it with ``.hydra/config.yaml``
    (``<run>/checkpoints/last.ckpt``, ``<run>/hpc_ckpt_1.ckpt``, ``<run>/checkpoints/last.recalibrated.ckpt``)."""
    for folder in list(ckpt.parents)[:3]:
        if (folder / ".hydra" / "config.yaml").is_file():
            return folder
    return None


def _read_setting(path: Path, depth: int = 0) -> _Setting:
    """What the run in ``path`` was: its Hydra files, read as a resumed run's where it resumed a checkpoint.
    ``OSError`` or ``yaml.YAMLError`` when a file of ``.hydra/`` (or ``resumed_config.yaml``) is unreadable."""
    setting = _read_hydra_files(path)
    if not (path / RESUMED_CONFIG).is_file():
        return setting
    return _read_resumed(path, setting, depth)


def _read_hydra_files(path: Path) -> _Setting:
    """The config, group choices, overrides and ``hydra`` section that Hydra wrote into ``path/.hydra/``."""
    hydra_dir = path / ".hydra"
    config = _read_yaml(hydra_dir / "config.yaml") or {}
    hydra_cfg = (_read_yaml(hydra_dir / "hydra.yaml") or {}) if (hydra_dir / "hydra.yaml").is_file() else {}
    has_overrides = (hydra_dir / "overrides.yaml").is_file()
    overrides = [str(o) for o in (_read_yaml(hydra_dir / "overrides.yaml") or [])] if has_overrides else []
    hydra = dict(hydra_cfg.get("hydra") or {})
    choices = dict((hydra.get("runtime") or {}).get("choices") or {})
    return _Setting(config, choices, overrides, hydra)


def _resumed_checkpoint(path: Path, own: _Setting, effective: dict[str, Any]) -> Path | None:
    """The checkpoint a resumed run started from (absolute; a relative ``ckpt_path`` is taken from where the
    resume was started), ``None`` where neither config names one."""
    text = effective.get("ckpt_path") or own.config.get("ckpt_path")
    if not text:
        return None
    ckpt = Path(str(text)).expanduser()
    if not ckpt.is_absolute():
        ckpt = Path(str((own.hydra.get("runtime") or {}).get("cwd") or path)) / ckpt
    return Path(os.path.normpath(ckpt))


def _read_resumed(path: Path, own: _Setting, depth: int) -> _Setting:
    """A resumed run (module docstring): the config of ``resumed_config.yaml``, the choices and overrides of the
    run that wrote its checkpoint with the resume's own (``own``: its Hydra files) laid over them."""
    effective = _read_yaml(path / RESUMED_CONFIG) or {}
    ckpt = _resumed_checkpoint(path, own, effective)
    if ckpt is None:
        return _Setting(effective, own.choices, own.overrides, own.hydra)
    overrides = [o for o in own.overrides if override_key(o) != "ckpt_path"]
    named = {override_key(o) for o in overrides}  # groups (and keys) the resume's command line names
    origin_dir = _checkpoint_run_dir(ckpt)
    origin, why = None, "no run directory with .hydra/ holds that checkpoint"
    if origin_dir is not None and origin_dir.resolve() != path.resolve() and depth < _MAX_RESUMES:
        try:
            origin = _read_setting(origin_dir, depth + 1)
        except (OSError, yaml.YAMLError) as e:
            why = f"the run directory that holds it, {origin_dir}, is unreadable ({e})"
    if origin is None:
        unknown = sorted(g for g, v in own.choices.items() if not (_own_group(g) or g in named) and v is not None)
        kept = {g: (None if g in unknown else v) for g, v in own.choices.items()}  # None: unknown, not the default
        note = (
            f"resumed from {ckpt}, but {why}: the original run's choices ({', '.join(unknown)}) and overrides "
            f"are unknown; its config values come from {RESUMED_CONFIG}"
        )
        return _Setting(effective, kept, overrides, own.hydra, ckpt, [note])
    choices = dict(origin.choices)
    choices.update({g: v for g, v in own.choices.items() if _own_group(g) or g in named})
    changed = []
    effective_node, origin_node = OmegaConf.create(effective), OmegaConf.create(origin.config)
    for override in overrides:
        key = override_key(override)
        if key in own.choices or key in origin.choices:  # a group: did its choice change?
            if not values_equal(own.choices.get(key), origin.choices.get(key)):
                changed.append(override)
            continue
        now, before = config_value(effective_node, key, _MISSING), config_value(origin_node, key, _MISSING)
        if (now is _MISSING) != (before is _MISSING) or not (now is _MISSING or values_equal(now, before)):
            changed.append(override)
    keys = {override_key(o) for o in changed}
    merged = [o for o in origin.overrides if override_key(o) not in keys] + changed
    return _Setting(effective, choices, merged, own.hydra, ckpt, list(origin.notes))


def _only_a_start(path: Path) -> bool:
    """Whether a run directory holds nothing but what Hydra writes before the task starts (``.hydra/``, a log)."""
    try:
        return all(e.name == ".hydra" or (e.is_file() and e.suffix == ".log") for e in path.iterdir())
    except OSError:
        return False


def _read_run(path: Path) -> Run | UnfinishedRun:
    try:
        setting = _read_setting(path)
    except (OSError, yaml.YAMLError) as e:
        return UnfinishedRun(path, f".hydra/ or {RESUMED_CONFIG} is not readable ({e})")
    metrics, reason = _read_metrics(path / "metrics.json")
    if metrics is None:
        if _only_a_start(path):
            reason += (
                "; it holds only .hydra/ and the log: a run still starting, or a start refused before training "
                "(left by a version before such starts removed their directory; safe to delete once no run uses it)"
            )
        return UnfinishedRun(path, reason)
    run = Run(
        path=path, metrics=metrics, choices=setting.choices, config=setting.config, overrides=setting.overrides,
        hydra=setting.hydra, resumed_from=setting.resumed_from, notes=list(setting.notes),
    )  # fmt: skip
    run.incomplete = incomplete_reason(run)
    return run


# ---------------------------------------------------------------------------------------- finished or not
def _limited(value: Any) -> bool:
    """Whether a ``trainer.limit_*_batches`` value leaves batches out: an integer is a number of batches, a
    fraction below 1.0 a share of them; ``null`` and 1.0 are all."""
    if value is None or isinstance(value, bool):
        return False
    if isinstance(value, str):
        try:
            value = int(value) if value.strip().lstrip("+-").isdigit() else float(value)
        except ValueError:
            return False
    return isinstance(value, int) or (isinstance(value, float) and value < 1.0)


def _smoke(value: Any) -> bool:
    """Whether ``trainer.fast_dev_run`` is on: ``true``, or a number of batches above 0."""
    if isinstance(value, str):
        value = value.strip().lower()
        return value not in ("", "false", "0", "null", "none")
    return bool(value)


def _epochs_done(checkpoint: Path) -> tuple[int, int, bool]:
    """``(epochs, steps, mid_epoch)`` of a training checkpoint: the epochs whose training batches were all done
    (Lightning's count of epochs processed), the optimiser steps, and whether it was written inside an epoch.

    The file is opened memory-mapped: only its small pickled part is read, not the weights. Raises ``OSError``
    or ``RuntimeError``/``ValueError``/``KeyError`` for a file that is no readable checkpoint."""
    import torch

    state = torch.load(checkpoint, map_location="cpu", weights_only=True, mmap=True)
    steps = int(state.get("global_step", 0) or 0)
    if has_loop_state(state):
        return epoch_resumed_in(state), steps, batches_done_in_epoch(state) > 0
    return int(state.get("epoch", -1)) + 1, steps, False  # a checkpoint without loop state: its epoch's end


def incomplete_reason(run: Run) -> str | None:
    """Why ``run``, although it wrote ``metrics.json``, does not count as a finished run (None: it does).

    * ``trainer.fast_dev_run``: ``fast_dev_run`` (one batch of each loop);
    * ``trainer.limit_test_batches`` below all batches (an integer, or a fraction below 1.0): its metrics are
      of part of the test set. (``limit_train_batches`` and ``limit_val_batches`` are a training budget like
      ``max_epochs``: a run that trained to the end of that budget is finished);
    * a run that trained (``train`` true) whose last checkpoint (``checkpoints/last.ckpt``, else the one a
      resumed run started from) has fewer epochs than ``trainer.max_epochs`` of its config (a resumed run's
      ``resumed_config.yaml``) and fewer steps than a ``trainer.max_steps`` it sets: ``unfinished: stopped after
      epoch E of N`` (or ``during epoch E``), e.g. ended by ``trainer.max_time``.

    A ``train=false`` run only tests its checkpoint and is never unfinished; a run without a checkpoint (no
    ``model_checkpoint`` callback) is counted as finished, as nothing says otherwise."""
    if _smoke(run.get("trainer.fast_dev_run", False)):
        return "fast_dev_run"
    value = run.get("trainer.limit_test_batches", None)
    if _limited(value):
        share = f"at most {value} batches" if float(value) >= 1 else f"{float(value):.0%} of the batches"
        return f"limit_test_batches={value}: tested on {share} of the test set"
    if str(run.get("train", True)).lower() == "false":
        return None
    max_epochs, max_steps = run.get("trainer.max_epochs", None), run.get("trainer.max_steps", None)
    max_epochs = max_epochs if isinstance(max_epochs, int) and not isinstance(max_epochs, bool) else None
    max_steps = max_steps if isinstance(max_steps, int) and not isinstance(max_steps, bool) else None
    if not (max_epochs and max_epochs > 0):
        return None  # no epoch limit: the run ended at its steps or time, as configured
    checkpoint = run.path / LAST_CHECKPOINT
    if not checkpoint.is_file() and run.resumed_from is not None:
        checkpoint = run.resumed_from  # a resume with nothing left to train writes no checkpoint of its own
    if not checkpoint.is_file():
        return None
    try:
        epochs, steps, mid_epoch = _epochs_done(checkpoint)
    except Exception as e:  # noqa: BLE001  (any unreadable file: torch raises many kinds)
        run.notes.append(f"{checkpoint} is not readable ({type(e).__name__}): whether it finished is unknown")
        return None
    if epochs >= max_epochs or (max_steps is not None and max_steps > 0 and steps >= max_steps):
        return None
    where = f"during epoch {epochs + 1}" if mid_epoch else f"after epoch {epochs}"
    return f"unfinished: stopped {where} of {max_epochs}"


def counted_runs(runs: list[Run], include_unfinished: bool = False) -> tuple[list[Run], list[Run]]:
    """``(counted, left_out)``: the runs that enter a table's means, and those that do not (not finished as
    configured, :attr:`Run.incomplete`), unless ``include_unfinished`` counts every run with metrics."""
    if include_unfinished:
        return list(runs), []
    return [r for r in runs if not r.incomplete], [r for r in runs if r.incomplete]


def find_runs(paths: list[str | Path]) -> tuple[list[Run], list[UnfinishedRun]]:
    """Every run directory at or below ``paths`` (a run, a sweep, or a folder of sweeps), read.

    ``FileNotFoundError`` for a path that does not exist, ``ValueError`` for one that holds no run."""
    runs: list[Run] = []
    unfinished: list[UnfinishedRun] = []
    seen: set[Path] = set()
    for p in paths:
        root = Path(p)
        if not root.exists():
            raise FileNotFoundError(
                f"{root}: no such directory (give a run or sweep directory, "
                "e.g. logs/table7/multiruns/<date>_<time>_<pid>)"
            )
        found = sorted({c.parent.parent.resolve() for c in root.glob("**/.hydra/config.yaml")})
        if not found:
            raise ValueError(f"{root}: no run directory (a folder with .hydra/config.yaml) at or below it")
        for run_dir in found:
            if run_dir in seen:
                continue
            seen.add(run_dir)
            item = _read_run(run_dir)
            (runs if isinstance(item, Run) else unfinished).append(item)
    return runs, unfinished
