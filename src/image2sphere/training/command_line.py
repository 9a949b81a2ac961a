"""A mistyped key or group option on the command line of ``src.train``, ``src.eval`` or ``src.predict``: one
line that names it and the closest existing names, before Hydra composes the config.

Hydra answers a wrong override with its own report, composed before our task runs: ``lmx=4`` gets
"Could not override 'lmx'. To append to your config use +lmx=4" (and ``+lmx=4`` then trains with the
default ``lmax`` and no warning), ``model=wigner`` gets 30 lines of every option of every group. Each
entry point therefore calls :func:`check_command_line` before ``main()``; it reads ``sys.argv`` as Hydra
does (Hydra's own argument and override parsers) and refuses, with ``Error: <line>`` on stderr and exit
status 1 and before any run directory exists:

* **a group option that does not exist** (``model=wigner``, ``dataset=pascal3D``, ``hydra/launcher=slurmm``,
  ``experiment=fidelity/aftr``, each option of a sweep ``model=i2s,wigner``), naming the closest options
  (:func:`difflib.get_close_matches`); the options are those of the config search path (``conf/``, Hydra's
  own, the plugins'), as Hydra finds them;
* **a key that does not exist** (``lmx=4``, ``trainer.max_epoch=3``, ``hydra.run.dirr=...``, ``~lmx``),
  naming the closest keys at the same level of the composed config;
* **a key added with ``+``** (or ``++``) that is a close misspelling of an existing key at the same level
  (``+lmx=4``: did you mean ``lmax``?). A genuinely new key (``+trainer.profiler=simple``,
  ``+model.foo=1``) has no existing key that close (:data:`ADDED_KEY_CUTOFF`) and is accepted;
* in ``src.eval`` and ``src.predict``, **a model or encoder override** (``model=...``, ``model.net.x=...``,
  ``encoder=...``): they rebuild the network their checkpoint holds;
* **a group that the config does not have** (``dataset=symsol1`` in ``src.predict``), naming its groups.

Group options are checked against the config repository alone. Keys need a composed config, and only when
some override sets or removes a key or picks a group that is not in the primary config's own defaults list
(a command line of group options from that list, or none at all, composes nothing). Which keys a config has
follows from its groups, not from the values a command line sets: the config of the group overrides alone
(a sweep's first value standing for the sweep) is composed once per process and set of groups, and a key it
has is accepted. Only a key it lacks is judged on the config composed with the whole command line, where a
value may have made it (``model.net={...}``); when that composition fails, the key is unknown.

Not checked (Hydra behaves as before): with ``HYDRA_FULL_ERROR=1``; with ``--help``, ``--hydra-help``,
``--info``, ``--shell-completion``, ``--config-path`` or ``--experimental-rerun``; a sweep over a glob or an
interval; keys of a multirun whose sweeper is not Hydra's basic one (the table and Optuna sweepers compose
each job with overrides of their own, which may bring the key). Anything this check cannot judge, or an
error inside it, leaves the command line to Hydra.
"""

from __future__ import annotations

import contextlib
import difflib
import io
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["ADDED_KEY_CUTOFF", "CONF_DIR", "check_command_line", "command_line_problem"]

log = logging.getLogger(__name__)

#: the configs of the entry points (``src/train.py`` ... read ``../conf``)
CONF_DIR = Path(__file__).resolve().parents[3] / "conf"
#: how alike (``difflib`` ratio) a key added with ``+`` and an existing key must be to refuse the added one:
#: ``lmx``/``lmax`` is 0.86; ``profiler`` and the closest key of ``trainer`` (``precision``) are 0.35
ADDED_KEY_CUTOFF = 0.8
# how alike a name must be to be suggested for an unknown key or option (difflib's default)
SUGGEST_CUTOFF = 0.6
# flags after which the command line is not a run: Hydra prints something and exits
_NOT_A_RUN = ("help", "hydra_help", "shell_completion", "info", "experimental_rerun", "config_path")
# the entry points that rebuild the network their checkpoint holds, and the sections that describe it: an
# override of those has no effect there
_FROM_CHECKPOINT = {"eval", "predict"}
_NETWORK_SECTIONS = ("model", "encoder")
_BASIC_SWEEPER = "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"


class _Unjudged(Exception):
    """The check cannot judge this command line: Hydra reports whatever is wrong with it."""


def check_command_line(config_name: str, argv: Sequence[str] | None = None) -> None:
    """Refuse a mistyped key or group option of ``argv`` (default: ``sys.argv[1:]``) with one line on stderr and
    exit status 1 (see the module docstring); return when there is none, when ``HYDRA_FULL_ERROR=1`` is set
    or when the command line is not a run. ``config_name``: the entry point's config (``train.yaml``)."""
    if os.environ.get("HYDRA_FULL_ERROR") == "1":
        return
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        problem = command_line_problem(config_name, argv)
    except Exception as e:  # noqa: BLE001 - the check never stands in Hydra's way: Hydra reports the rest
        log.debug("command-line check skipped: %r", e)
        return
    if problem is not None:
        print(f"Error: {problem}", file=sys.stderr)
        raise SystemExit(1)


def command_line_problem(config_name: str, argv: Sequence[str], conf_dir: Path = CONF_DIR) -> str | None:
    """The one-line refusal of ``argv`` (the arguments after ``python -m src.<entry>``), or ``None``."""
    args = _parse_arguments(argv)
    if args is None or any(getattr(args, flag, None) for flag in _NOT_A_RUN) or not args.overrides:
        return None
    if not conf_dir.is_dir():
        return None
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    entry = Path(config_name).stem
    command = f"python -m src.{entry}"
    try:
        overrides = OverridesParser.create().parse_overrides(args.overrides)
    except HydraException:
        return None  # a syntax error: Hydra's message shows where
    try:
        loader = _loader(conf_dir, args.config_dir)
        repo = loader.repository
        for override in overrides:
            problem = _from_checkpoint(override, entry, command) or _group_problem(override, repo, command)
            if problem:
                return problem
        return _key_problem(overrides, loader, args.config_name or config_name, bool(args.multirun), command)
    except _Unjudged:
        return None


# ---------------------------------------------------------------------------------------------- parsing
def _parse_arguments(argv: Sequence[str]) -> Any:
    """Hydra's own reading of the command line (``None`` where argparse would refuse it: Hydra says why)."""
    from hydra._internal.utils import get_args_parser

    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        try:
            return get_args_parser().parse_args(list(argv))
        except SystemExit:
            return None


def _loader(conf_dir: Path, config_dir: str | None):
    """A config loader on the search path Hydra builds for the entry points (plugins included)."""
    from hydra._internal.config_loader_impl import ConfigLoaderImpl
    from hydra._internal.utils import create_config_search_path
    from hydra.core.config_search_path import SearchPathQuery

    search_path = create_config_search_path(f"file://{conf_dir}")
    if config_dir is not None:  # --config-dir, as Hydra adds it
        if not os.path.isdir(config_dir):
            raise _Unjudged
        search_path.prepend("command-line", f"file://{os.path.abspath(config_dir)}", SearchPathQuery("schema"))
    return ConfigLoaderImpl(config_search_path=search_path)


def _values(override) -> list[Any]:
    """The values an override gives its key: each value of a sweep, the elements of a list, else the one."""
    from hydra.core.override_parser.types import Glob, IntervalSweep

    value = override.value()
    if isinstance(value, Glob | IntervalSweep):
        raise _Unjudged  # the options it stands for depend on the sweeper
    if override.is_sweep_override():
        return list(override.sweep_iterator())
    return list(value) if isinstance(value, list) else [value]


def _first_value(override) -> str:
    """``override`` as an override of one value: a sweep's first value stands for the sweep."""
    if not override.is_sweep_override():
        return override.input_line
    from hydra.core.override_parser.types import Glob, IntervalSweep

    if isinstance(override.value(), Glob | IntervalSweep):
        raise _Unjudged
    return f"{override.get_key_element()}={next(iter(override.sweep_string_iterator()))}"


def _closest(name: str, names: Sequence[str], cutoff: float = SUGGEST_CUTOFF, parts: bool = True) -> list[str]:
    """The names most like ``name`` (case does not count), at most three: with ``parts``, those that contain
    it first (``wigner``: ``wigner_regression``), then those :func:`difflib.get_close_matches` finds."""
    lower: dict[str, str] = {}
    for n in names:
        lower.setdefault(str(n).lower(), str(n))
    typed = name.lower()
    alike = difflib.get_close_matches(typed, list(lower), n=3, cutoff=cutoff)
    found = sorted((n for n in lower if typed in n and n != typed), key=len) if parts and len(typed) >= 3 else []
    return [lower[m] for m in dict.fromkeys(found + alike)][:3]


def _either(names: list[str]) -> str:
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} or {names[-1]}"


# ---------------------------------------------------------------------------------------------- groups
def _from_checkpoint(override, entry: str, command: str) -> str | None:
    """In ``src.eval`` and ``src.predict``, an override of the model or its encoder, which their checkpoint
    decides."""
    top = override.key_or_group.replace("/", ".").split(".")[0]
    if entry not in _FROM_CHECKPOINT or top not in _NETWORK_SECTIONS:
        return None
    given = override.input_line
    return (
        f"{given}: {command} uses the network its checkpoint holds (ckpt_path=...), whatever model that is; "
        f"drop {given} (to train with it: python -m src.train {given.lstrip('+~')})"
    )


def _options(repo, group: str, depth: int = 0) -> list[str]:
    """Every option of ``group``, those of its subfolders as ``sub/option`` (``experiment=fidelity/after``)."""
    from hydra.core.object_type import ObjectType

    out = list(repo.get_group_options(group, ObjectType.CONFIG))
    if depth < 3:
        for sub in repo.get_group_options(group, ObjectType.GROUP):
            out += [f"{sub}/{option}" for option in _options(repo, f"{group}/{sub}", depth + 1)]
    return out


def _group_problem(override, repo, command: str) -> str | None:
    """An option of a group that the config search path does not hold, or a group path that is none."""
    group = override.key_or_group
    if override.is_delete():
        return None
    if not repo.group_exists(group):
        if "/" not in group:
            return None  # a key, checked with the composed config
        parent, _, name = group.rpartition("/")
        from hydra.core.object_type import ObjectType

        groups = repo.get_group_options(parent, ObjectType.GROUP) if repo.group_exists(parent) else []
        close = _closest(name, groups)
        hint = f"; did you mean {_either([f'{parent}/{c}' for c in close])}?" if close else ""
        return f"{group} is not a config group{hint} (the groups: {command} --help)"
    for value in _values(override):
        if value is None or not isinstance(value, str):
            continue  # null: no option of the group
        if repo.config_exists(f"{group}/{value}"):
            continue
        close = _closest(value, _options(repo, group))
        found = f"; closest: {', '.join(close)}" if close else ""
        return f"{group}={value} is not an option of {group}{found} (all options: {command} --help)"
    return None


# ---------------------------------------------------------------------------------------------- keys
def _key_problem(overrides: list, loader, config_name: str, multirun: bool, command: str) -> str | None:
    """A key the composed config does not have (see the module docstring); composes only when needed."""
    repo = loader.repository
    groups = [o for o in overrides if repo.group_exists(o.key_or_group)]
    added = [o for o in overrides if (o.is_add() or o.is_force_add()) and o not in groups]
    own_groups = _primary_groups(repo, config_name)
    if len(groups) == len(overrides) and all(
        not (o.is_add() or o.is_delete()) and o.key_or_group in own_groups for o in groups
    ):
        return None  # options of the primary config's own groups, checked above: nothing to compose
    added_paths = [o.key_or_group for o in added]

    def under_added(override) -> bool:  # set under a key this command line adds
        return any(override.key_or_group == p or override.key_or_group.startswith(p + ".") for p in added_paths)

    keys = [o for o in overrides if o not in groups and o not in added and not under_added(o)]
    # The keys a config has follow from its groups, not from the values set: the config of the group overrides
    # alone (composed once per process and set of groups) judges every key that it has. Only a key it lacks
    # (unknown, or made by a value, as model.net={...}) needs the config of the whole command line.
    structure = _compose_groups(loader, config_name, [_first_value(o) for o in groups])
    if structure is not None and all(_unknown_key(o, structure, command, SUGGEST_CUTOFF, True) is None for o in keys):
        return _added_key_problem(added, structure, command)
    composed = [_first_value(o) for o in overrides if o not in added]
    base = _compose(loader, config_name, composed)
    if base is None:  # some override does not fit: the config of the group overrides alone says which
        base = structure
        if base is None:
            return _group_not_in_defaults(groups, loader, config_name, command)
        if multirun or "MULTIRUN" in str(base.hydra.get("mode")):
            if _sweeper(base) != _BASIC_SWEEPER:
                return None  # its jobs are composed with overrides of the sweeper's own
        for override in keys:
            problem = _unknown_key(override, base, command, SUGGEST_CUTOFF, always=True)
            if problem:
                return problem
        return None
    return _added_key_problem(added, base, command)


def _added_key_problem(added: list, cfg, command: str) -> str | None:
    """The line for a key added with ``+`` that looks like a misspelling of a key ``cfg`` has."""
    for override in added:
        problem = _unknown_key(override, cfg, command, ADDED_KEY_CUTOFF, always=False)
        if problem:
            return problem
    return None


def _group_not_in_defaults(groups: list, loader, config_name: str, command: str) -> str | None:
    """A group override (without ``+``) of a group that the config's defaults list does not name: the config
    has no such choice to change (``dataset=...`` in ``src.predict``)."""
    cfg = _compose(loader, config_name, [])
    if cfg is None:
        return None
    choices = {str(k) for k in cfg.hydra.runtime.choices}
    for override in groups:
        if override.is_add() or override.is_force_add() or override.is_delete():
            continue
        if override.key_or_group not in choices:
            own = ", ".join(sorted(c for c in choices if not c.startswith("hydra")))
            return (
                f"{override.input_line}: {override.key_or_group} is not a config group of {command} (its groups: {own})"
            )
    return None


def _primary_groups(repo, config_name: str) -> set[str]:
    """The groups named in the primary config's own defaults list (``model``, ``dataset``, ...)."""
    result = repo.load_config(config_name)
    defaults = getattr(result, "defaults_list", None) or []
    return {str(d.group) for d in defaults if getattr(d, "group", None) and not getattr(d, "override", False)}


# the configs of group overrides alone, by search path, config and overrides: a process that checks many command
# lines (a test session, a notebook) composes each set of groups once
_GROUP_CONFIGS: dict[tuple, Any] = {}
_GROUP_CONFIGS_KEPT = 32


def _compose_groups(loader, config_name: str, overrides: list[str]):
    """:func:`_compose` of group overrides, kept per process (read only: the caller never edits it)."""
    search_path = tuple((e.provider, e.path) for e in loader.get_search_path().get_path())
    key = (search_path, config_name, tuple(overrides))
    if key not in _GROUP_CONFIGS:
        if len(_GROUP_CONFIGS) >= _GROUP_CONFIGS_KEPT:
            _GROUP_CONFIGS.pop(next(iter(_GROUP_CONFIGS)))
        _GROUP_CONFIGS[key] = _compose(loader, config_name, overrides)
    return _GROUP_CONFIGS[key]


def _compose(loader, config_name: str, overrides: list[str]):
    """The config with ``overrides`` (and Hydra's node), or ``None`` when Hydra cannot compose it."""
    from hydra.types import RunMode

    try:
        return loader.load_configuration(config_name, list(overrides), run_mode=RunMode.RUN, from_shell=True)
    except Exception:  # noqa: BLE001 - any composition error: the caller looks for the override at fault
        return None


def _sweeper(cfg) -> str | None:
    from omegaconf import OmegaConf

    return OmegaConf.select(cfg, "hydra.sweeper._target_", default=None)


def _unknown_key(override, cfg, command: str, cutoff: float, always: bool) -> str | None:
    """The line for ``override``'s key when its first missing part is unknown to ``cfg``: with ``always``, every
    missing key (a suggestion when one is close); otherwise only one that is within ``cutoff`` of an existing key
    at its level (a ``+`` key that looks mistyped)."""
    from omegaconf import DictConfig, OmegaConf

    parts = override.key_or_group.split(".")
    node = cfg
    for i, part in enumerate(parts):
        if not isinstance(node, DictConfig):
            return None  # below a value that is not a mapping: Hydra's own message says so
        if part in node.keys():  # a ??? value too, which "in node" leaves out
            child = node._get_node(part)
            if child._is_interpolation():
                child = OmegaConf.select(cfg, ".".join(parts[: i + 1]), default=None, throw_on_resolution_failure=False)
            node = child
            continue
        parent = ".".join(parts[:i])
        siblings = [str(k) for k in node.keys()]
        if parent == "" and "hydra" not in siblings:
            siblings.append("hydra")
        close = _closest(part, siblings, cutoff, parts=always)
        if not close and not always:
            return None
        key = ".".join(parts[: i + 1])
        if close:
            names = [f"{parent}.{c}" if parent else c for c in close]
            return f"{key} is not a config key; did you mean {_either(names)}?"
        return f"{key} is not a config key of {command} (every key: {command} --cfg job)"
    return None
