"""The run's config before any work starts: one check of its values, and the config of a resumed run.

:func:`check_train_config`, :func:`check_eval_config` and :func:`check_predict_config` refuse invalid
values (naming the key and what is allowed) before a dataset is read or rendered, a network built or
a file written. They also take the old names of renamed keys (:data:`RENAMED_KEYS`, e.g. predict's
``level``, now ``eval_grid_level`` as in train and eval): an old key that is given is used under its
new name, with a one-line warning naming it. The old names are removed in the next release.

:func:`resume_config` decides what a run started with ``ckpt_path=...`` trains: the checkpoint
holds the resolved config of the run that wrote it (``run_config``), and

* **what is trained** comes from there: the sections ``model`` (network, optimiser, schedule,
  grid levels), ``dataset`` and ``encoder``, the top-level ``lmax``, ``train_grid_level``,
  ``eval_grid_level`` and ``seed``, and the trainer's schedule (``trainer.max_epochs``, ``max_steps``,
  ``min_epochs``, ``precision``, ``accumulate_grad_batches``, ``gradient_clip_val``);
* **where and how the run goes** (run directory, loggers, callbacks, devices) comes from the new
  command line and its defaults;
* any key the new command line changes explicitly (``trainer.max_epochs=60``, ``dataset=symsol1``,
  ``model.optimizer.lr=1e-4``, an ``experiment=...`` file) wins over the checkpoint.

"Changes explicitly" is decided by Hydra itself: the config is composed once with the command
line's overrides and once without, and the keys whose values differ are the explicit ones.

Another model cannot continue a checkpoint (:func:`check_same_model`): a ``model=`` option other than the
one the checkpoint's run was trained with (its run directory's ``.hydra/`` says which), or a command line
that changes the class of the model or of its network, is refused before anything is written. A change of
the network's size (``model.net.*``) is refused once the network is built, when the checkpoint's weights do
not fit it (:func:`~image2sphere.training.checkpoint.check_resumed_weights`).
"""

from __future__ import annotations

import copy
import logging
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict

from image2sphere.checks import ConfigError, check_int
from image2sphere.config_text import override_key
from image2sphere.data.workers import check_num_workers
from image2sphere.so3.grid import check_grid_levels

__all__ = [
    "RENAMED_KEYS",
    "check_choice",
    "check_same_model",
    "check_eval_config",
    "check_predict_config",
    "check_train_config",
    "deprecated_name",
    "describe_run",
    "resume_config",
    "stored_model_choice",
]

log = logging.getLogger(__name__)

# what a resumed run takes from its checkpoint unless the command line changes it
FROM_CHECKPOINT = ("model", "dataset", "encoder", "lmax", "train_grid_level", "eval_grid_level", "seed")
TRAINER_FROM_CHECKPOINT = (
    "max_epochs",
    "min_epochs",
    "max_steps",
    "precision",
    "accumulate_grad_batches",
    "gradient_clip_val",
)


# The old names of renamed keys, {old: new} per entry point (conf/train.yaml, eval.yaml, predict.yaml):
# one name per quantity in all three. Each old key stays in its config file as null for one release;
# given a value, it is used under the new name with a warning.
RENAMED_KEYS: dict[str, dict[str, str]] = {
    "train": {"model.refine_mode": "model.refine"},
    "eval": {},
    "predict": {"level": "eval_grid_level"},
}


def deprecated_name(old: str, new: str) -> None:
    """The one-line warning for a renamed key that was given under its old name."""
    log.warning("%s is deprecated and will be removed in the next release: use %s (its value is used)", old, new)


def _apply_renamed_keys(cfg: DictConfig, task: str) -> None:
    """Move the value of each old key of ``task`` that is given (not null) to its new key, with a warning,
    and drop the old keys from ``cfg``."""
    for old, new in RENAMED_KEYS[task].items():
        value = OmegaConf.select(cfg, old)
        if value is not None:
            deprecated_name(old, new)
            OmegaConf.update(cfg, new, value, force_add=True)
        parent, _, leaf = old.rpartition(".")
        node = OmegaConf.select(cfg, parent) if parent else cfg
        if isinstance(node, DictConfig) and leaf in node:
            with open_dict(node):
                del node[leaf]


def _int_at_least(cfg: DictConfig, key: str, minimum: int, allow_null: bool = False) -> None:
    value = OmegaConf.select(cfg, key)
    if value is None and (allow_null or OmegaConf.select(cfg, key, default="<absent>") == "<absent>"):
        return
    check_int(key, value, minimum, note=" or null" if allow_null else "")


def _check_levels(cfg: DictConfig, keys: list[str]) -> None:
    levels = {key: OmegaConf.select(cfg, key) for key in keys if OmegaConf.select(cfg, key) is not None}
    check_grid_levels(prefix="", **levels)


def check_choice(cfg: DictConfig, key: str, choices: tuple[str, ...], default: str) -> str:
    """``cfg[key]`` (``default`` when absent, e.g. in a config stored before the key existed) if it is one of
    ``choices``, else ``ValueError`` naming the key and the choices."""
    value = cfg.get(key, default)
    if value not in choices:
        raise ConfigError(f"{key} must be one of {', '.join(choices)}, got {value!r}")
    return value


def check_train_config(cfg: DictConfig) -> None:
    """Refuse invalid values of a training config (``python -m src.train``) before any work starts; renamed
    keys given under their old names are moved to the new ones (:data:`RENAMED_KEYS`)."""
    _apply_renamed_keys(cfg, "train")
    seed = cfg.get("seed")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
        raise ConfigError(f"seed must be an integer or null, got {seed!r}")
    for key in ("train", "test"):
        if not isinstance(cfg.get(key), bool):
            raise ConfigError(f"{key} must be true or false, got {cfg.get(key)!r}")
    check_choice(cfg, "recalibration", ("fit", "off"), default="fit")
    _int_at_least(cfg, "lmax", 0)
    _check_levels(
        cfg,
        ["train_grid_level", "eval_grid_level"]
        + [f"model.{k}" for k in ("train_grid_level", "val_grid_level", "eval_grid_level", "spread_grid_level")],
    )
    for key in ("dataset.image_size", "dataset.batch_size", "model.net.image_size"):
        _int_at_least(cfg, key, 1)
    check_num_workers(OmegaConf.select(cfg, "dataset.num_workers", default=0))  # an integer >= 0 or auto
    net_size, data_size = OmegaConf.select(cfg, "model.net.image_size"), OmegaConf.select(cfg, "dataset.image_size")
    if net_size is not None and data_size is not None and net_size != data_size:
        raise ConfigError(
            f"model.net.image_size={net_size} but dataset.image_size={data_size}: the network takes images of the "
            "size it was built for; set both to the same value"
        )
    _check_fused_clipping(cfg)
    max_epochs = OmegaConf.select(cfg, "trainer.max_epochs")
    valid_epochs = type(max_epochs) is int and (max_epochs >= 1 or max_epochs == -1)  # bool is not a count
    if max_epochs is not None and not valid_epochs:
        raise ConfigError(f"trainer.max_epochs must be an integer >= 1 (or -1: no limit), got {max_epochs!r}")


# Lightning's mixed-precision plugins ("16" and "bf16" are the older names)
MIXED_PRECISION = ("16-mixed", "bf16-mixed", "16", "bf16")


def _check_fused_clipping(cfg: DictConfig) -> None:
    """A fused optimiser (``conf/optimizer/``) unscales mixed precision's gradients inside its own step, so
    Lightning cannot clip them before it: refuse the three together at start-up instead of at the first step."""
    clip = OmegaConf.select(cfg, "trainer.gradient_clip_val")
    precision = str(OmegaConf.select(cfg, "trainer.precision", default="32-true"))
    fused = OmegaConf.select(cfg, "model.optimizer.fused", default=False)
    if fused is True and clip and precision in MIXED_PRECISION:
        raise ConfigError(
            f"model.optimizer.fused=true cannot clip gradients under trainer.precision={precision} "
            f"(trainer.gradient_clip_val={clip}): a fused optimiser unscales the gradients inside its step, after "
            "the clipping; set model.optimizer.fused=false to clip, or drop trainer.gradient_clip_val"
        )


def check_eval_config(cfg: DictConfig) -> None:
    """Refuse invalid values of an evaluation config (``python -m src.eval``) before any work starts; renamed
    keys given under their old names are moved to the new ones (:data:`RENAMED_KEYS`)."""
    _apply_renamed_keys(cfg, "eval")
    if cfg.get("ckpt_path") is None:
        raise ConfigError(
            "ckpt_path is required: python -m src.eval ckpt_path=logs/train/runs/<run>/checkpoints/last.ckpt"
        )
    _check_levels(cfg, ["eval_grid_level"])
    _int_at_least(cfg, "batch_size", 1, allow_null=True)
    _int_at_least(cfg, "plots", 0)
    if not isinstance(cfg.get("refine"), bool):
        raise ConfigError(f"refine must be true or false, got {cfg.get('refine')!r}")
    check_choice(cfg, "recalibration", ("auto", "fit", "off"), default="auto")
    check_choice(cfg, "batchnorm_statistics", ("stored", "recompute"), default="stored")
    _int_at_least(cfg, "batchnorm_batches", 1, allow_null=True)


def check_predict_config(cfg: DictConfig) -> None:
    """Move renamed keys of a prediction config (``python -m src.predict``) to their new names
    (:data:`RENAMED_KEYS`); :func:`image2sphere.inference.predict` checks the values."""
    _apply_renamed_keys(cfg, "predict")
    check_choice(cfg, "recalibration", ("auto", "off"), default="auto")


# ---------------------------------------------------------------------------------------------- resume
def _leaves(node: Any, prefix: str = "") -> dict[str, Any]:
    """``{dotted key: value}`` of every leaf of a config, interpolations resolved where they can be.

    Interpolations that cannot be resolved outside a running Hydra job (``${hydra:...}``) keep
    their text; nodes that interpolate other nodes (``encoder: ${encoder}``) are walked through.
    """
    out: dict[str, Any] = {}
    if isinstance(node, DictConfig):
        keys = list(node.keys())
        if not keys:
            out[prefix] = {}
        for key in keys:
            path = f"{prefix}.{key}" if prefix else str(key)
            try:
                value = node[key]
            except Exception:  # an interpolation that needs the running job
                value = OmegaConf.to_container(node, resolve=False)[key]
            out.update(_leaves(value, path))
    elif isinstance(node, ListConfig):
        try:
            out[prefix] = OmegaConf.to_container(node, resolve=True)
        except Exception:
            out[prefix] = OmegaConf.to_container(node, resolve=False)
    else:
        out[prefix] = node
    return out


def explicit_override_keys(config_name: str, overrides: list[str]) -> set[str]:
    """Dotted keys whose values the command line's ``overrides`` change (Hydra composes both ways)."""
    from hydra import compose

    def leaves(ov: list[str]) -> dict[str, Any]:
        return _leaves(compose(config_name=config_name, overrides=ov))

    with_ov, without = leaves(overrides), leaves([])
    return {k for k in set(with_ov) | set(without) if with_ov.get(k, "<absent>") != without.get(k, "<absent>")}


def _under(key: str, prefix: str) -> bool:
    """``key`` is ``prefix`` or lies below it (``a.b`` is under ``a``; ``ab`` is not)."""
    return key == prefix or key.startswith(prefix + ".")


def command_line() -> tuple[str, list[str]] | None:
    """The config name and the task overrides of the running Hydra job (``None`` outside Hydra)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return None
    hc = HydraConfig.get()
    return hc.job.config_name, list(hc.overrides.task)


def _merge(stored: Any, current: Any, prefix: str, explicit: set[str]) -> Any:
    """``stored`` with the leaves under ``prefix`` that the command line changed taken from ``current``."""
    if not any(_under(k, prefix) for k in explicit):
        return copy.deepcopy(stored)
    if prefix in explicit or not (isinstance(stored, dict) and isinstance(current, dict)):
        return copy.deepcopy(current)
    if f"{prefix}._target_" in explicit:  # another class: its arguments are another set
        return copy.deepcopy(current)
    out = {}
    for key in list(stored) + [k for k in current if k not in stored]:
        path = f"{prefix}.{key}"
        if key not in current:
            if not any(_under(k, path) for k in explicit):  # else the command line removed it
                out[key] = copy.deepcopy(stored[key])
        elif key not in stored:
            out[key] = copy.deepcopy(current[key])
        else:
            out[key] = _merge(stored[key], current[key], path, explicit)
    return out


def _class_name(model: Any, key: str) -> str:
    """The class name of ``model``'s ``key`` (``net._target_``), ``?`` when it has none."""
    node = model
    for part in key.split("."):
        node = node.get(part) if isinstance(node, dict) else None
    return str(node).rpartition(".")[2] if node else "?"


def stored_model_choice(ckpt_path: str | Path) -> str | None:
    """The ``model=`` option of the run that wrote the checkpoint at ``ckpt_path``, as its run directory's
    ``.hydra/`` says (followed back through a resume of a resume, :mod:`image2sphere.reporting.runs`);
    ``None`` when no run directory holds the checkpoint (a copied file) or it says nothing."""
    from image2sphere.reporting.runs import _checkpoint_run_dir, _read_setting

    run_dir = _checkpoint_run_dir(Path(ckpt_path).resolve())
    if run_dir is None:
        return None
    try:
        choice = _read_setting(run_dir).choices.get("model")
    except Exception:  # noqa: BLE001 - an unreadable .hydra/: the choice is unknown
        return None
    return str(choice) if choice else None


def check_same_model(stored: dict, current: dict, overrides: list[str], explicit: set[str], ckpt_path: str) -> None:
    """Refuse to resume the checkpoint at ``ckpt_path`` (its stored config ``stored``) with another model than the
    one it holds: a ``model=`` option on the command line (``overrides``) other than the option of the run that
    wrote it (:func:`stored_model_choice`), or, where that option is unknown, a command line that changes the
    class of the model or of its network (``explicit``: the keys the command line changes) to another than the
    checkpoint's. ``current``: the config the command line composes. Other changes of the network (its size) are
    refused when its weights do not fit (:func:`~image2sphere.training.checkpoint.check_resumed_weights`)."""
    given = next((o.split("=", 1)[1] for o in overrides if override_key(o) == "model" and "=" in o), None)
    fix = "to resume it, or leave out ckpt_path to train a new model"
    known = stored_model_choice(ckpt_path)
    if given is not None and known is not None:
        if given != known:
            raise ConfigError(
                f"ckpt_path={ckpt_path} holds a model={known} run; model={given} cannot continue it: "
                f"drop model={given} {fix}"
            )
        return
    if not explicit & {"model._target_", "model.net._target_"}:
        return
    old_model, new_model = stored.get("model") or {}, current.get("model") or {}
    for key in ("net._target_", "_target_"):
        before, after = _class_name(old_model, key), _class_name(new_model, key)
        if before != after:
            held = f"a model={known} run" if known else f"a run of {before} (model.{key})"
            change = f"model={given}" if given is not None else "the overrides that change the model"
            raise ConfigError(
                f"ckpt_path={ckpt_path} holds {held}; {change} ({after}) cannot continue it: drop {change} {fix}"
            )


def resume_config(cfg: DictConfig, ckpt: dict, ckpt_path: str) -> DictConfig:
    """The config a run resumed from ``ckpt`` runs with (see the module docstring); logs what came from where."""
    stored = ckpt["run_config"]
    current = OmegaConf.to_container(cfg, resolve=True)
    command = command_line()
    explicit: set[str] = set()
    overrides: list[str] = []
    if command is not None:
        overrides = [o for o in command[1] if override_key(o) != "ckpt_path"]
        if overrides:
            explicit = explicit_override_keys(command[0], overrides)
    check_same_model(stored, current, overrides, explicit, ckpt_path)
    result = copy.deepcopy(current)
    taken: list[str] = []
    for key in FROM_CHECKPOINT:
        if key in stored:
            result[key] = _merge(stored[key], current.get(key), key, explicit)
            taken.append(key)
    stored_trainer, trainer = stored.get("trainer") or {}, result.get("trainer")
    if isinstance(trainer, dict):
        for key in TRAINER_FROM_CHECKPOINT:
            path = f"trainer.{key}"
            if key in stored_trainer and path not in explicit:
                trainer[key] = stored_trainer[key]
        taken.append("trainer schedule")
    stored_leaves, result_leaves = _leaves(OmegaConf.create(stored)), _leaves(OmegaConf.create(result))
    checkpoint_keys = set(FROM_CHECKPOINT) | {f"trainer.{k}" for k in TRAINER_FROM_CHECKPOINT}
    from_command = sorted(
        k
        for k in explicit
        if any(_under(k, c) for c in checkpoint_keys)
        and stored_leaves.get(k, "<absent>") != result_leaves.get(k, "<absent>")
    )
    log.info(
        "Resuming from %s (epoch %s, global step %s): %s from the checkpoint's stored config%s",
        ckpt_path,
        ckpt.get("epoch"),
        ckpt.get("global_step"),
        ", ".join(taken),
        f"; from the command line: {', '.join(from_command)}" if from_command else "",
    )
    return OmegaConf.create(result)


# ---------------------------------------------------------------------------------------------- start-up
# what a protocol file (conf/protocol/) sets, with the command-line keys that replace it
PROTOCOL_KEYS = {
    "encoder": ("encoder",),
    "optimizer": ("optimizer", "model.optimizer"),
    "epochs": ("trainer.max_epochs",),
    "scheduler": ("scheduler", "model.scheduler"),
}


def _name(node: Any, default: str = "?") -> str:
    """The class name of a config node's ``_target_`` (``torch.optim.SGD`` -> ``SGD``)."""
    return str(node.get("_target_", default)).rsplit(".", 1)[-1] if node else default


def _kwargs(node: Any) -> str:
    """``a=1, b=2`` of a config mapping, without Hydra's own keys."""
    return ", ".join(f"{k}={v}" for k, v in (node or {}).items() if k not in ("_target_", "_partial_"))


def protocol_settings(cfg: DictConfig) -> dict[str, str]:
    """The four settings a protocol chooses (:data:`PROTOCOL_KEYS`), as they read in the start-up log."""
    model, enc = cfg.get("model") or {}, cfg.get("encoder") or {}
    weights = enc.get("weights")
    return {
        "encoder": f"{enc.get('name') or 'ResNet-' + str(enc.get('depth'))}, "
        f"{'weights ' + str(weights) if weights else 'random initialisation'}",
        "optimizer": f"{_name(model.get('optimizer'))}({_kwargs(model.get('optimizer'))})",
        "epochs": str(OmegaConf.select(cfg, "trainer.max_epochs")),
        "scheduler": f"{_name(model.get('scheduler'), 'none')}({_kwargs(model.get('scheduler'))}), "
        f"stepped every {model.get('scheduler_interval', 'epoch')}",
    }


def uses_band_limit(cfg: DictConfig) -> bool:
    """Whether the run's method has a band limit: a key ``lmax`` anywhere in its model config (I2S and its
    variants, the Wigner-D regression, the Fourier MLP take the top-level ``lmax``; a flow, IPDF or a
    regressor has none). Also right for a resumed run, whose config is the checkpoint's, resolved.
    ``True`` when the config has no model section (nothing to tell)."""
    model = cfg.get("model")
    if not isinstance(model, DictConfig):
        return True

    def has_lmax(node) -> bool:
        if isinstance(node, dict):
            return "lmax" in node or any(has_lmax(v) for v in node.values())
        if isinstance(node, list):
            return any(has_lmax(v) for v in node)
        return False

    return has_lmax(OmegaConf.to_container(model, resolve=False))


def describe_run(
    cfg: DictConfig,
    choices: dict[str, str] | None = None,
    overrides: list[str] = (),
    protocol: dict[str, str] | None = None,
) -> str:
    """Lines that say what a training run trains: data, network, encoder, optimiser and schedule.

    ``choices`` are Hydra's group choices of the run (``hydra.runtime.choices``; ``None`` for a
    resumed run, whose values come from its checkpoint), ``overrides`` its command-line overrides
    and ``protocol`` the :func:`protocol_settings` of its protocol file alone: each of the four
    settings is marked as the protocol's, the command line's, or changed by another config file.
    """
    choices = {k: v for k, v in (choices or {}).items() if v is not None}
    keys = [override_key(o) for o in overrides]
    others = ", ".join(f"{g}={choices[g]}" for g in ("experiment", "debug", "hparams_search") if g in choices)
    settings = protocol_settings(cfg)

    def source(what: str) -> str:
        if any(_under(k, p) for k in keys for p in PROTOCOL_KEYS[what]):
            return "  [command line]"
        if protocol is None or "protocol" not in choices:
            return ""
        if protocol[what] == settings[what]:
            return f"  [protocol={choices['protocol']}]"
        return f"  [{others or 'another config file'}]"

    def choice(group: str) -> str:
        return f"{choices[group]}: " if group in choices else ""

    data, net = cfg.get("dataset") or {}, OmegaConf.select(cfg, "model.net") or {}
    band_limit = f"lmax {cfg.get('lmax')}, " if uses_band_limit(cfg) else ""  # a flow or IPDF has none
    lines = [
        f"  data       {choice('dataset')}{_name(data)} from {data.get('root') or data.get('render_dir')}, "
        f"{data.get('image_size')} px, batch {data.get('batch_size')}",
        f"  model      {choice('model')}{_name(net)}, {band_limit}"
        f"grid levels {cfg.get('train_grid_level')} (training) and {cfg.get('eval_grid_level')} (test)",
    ] + [f"  {what:<10} {choice(what)}{settings[what]}{source(what)}" for what in PROTOCOL_KEYS]
    if "protocol" in choices:
        head = (
            f"This run trains (dataset={choices.get('dataset')} brings protocol={choices['protocol']}, "
            f"conf/protocol/{choices['protocol']}.yaml; docs/configuration.md):"
        )
    else:
        head = "This run trains (values from the checkpoint where it resumes one):"
    if others:
        lines.append(f"  also       {others}")
    return "\n".join([head, *lines])
