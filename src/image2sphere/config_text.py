"""What Hydra wrote, read with Hydra's and OmegaConf's own parsers: the key of a command-line override and
the value of a dotted key in a composed config.

Both are read where a run's files are read back (``src.tables``, a resumed run's checkpoint, the checks
of a command line), so this module imports only Hydra and OmegaConf, never Lightning.
"""

from __future__ import annotations

import functools
from typing import Any

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

__all__ = ["config_value", "override_key"]


@functools.cache
def _parser() -> Any:
    from hydra.core.override_parser.overrides_parser import OverridesParser

    return OverridesParser.create()  # no config loader: keys and values only, no group listing


@functools.lru_cache(maxsize=4096)  # a table reads the same runs' overrides once per setting it looks up
def override_key(override: str) -> str:
    """The key or group a command-line override sets, as Hydra parses it: ``+a.b=1`` -> ``a.b``,
    ``dataset=symsol1`` -> ``dataset``, ``~trainer.devices`` -> ``trainer.devices``, ``dataset@data=x`` ->
    ``dataset``. A text Hydra cannot parse (a hand-edited ``overrides.yaml``) is its own key."""
    from hydra.errors import HydraException

    try:
        return str(_parser().parse_override(override).key_or_group)
    except HydraException:
        return override


def config_value(config: DictConfig | dict, key: str, default: Any = None) -> Any:
    """The value of dotted ``key`` in ``config`` (``default`` where it is absent or ``???``), interpolations
    resolved by OmegaConf; one that cannot be resolved here (a resolver this process has not registered, or
    ``${hydra:...}`` outside a Hydra job, as in ``src.tables``) reads as ``default`` too. Nodes come back as
    plain dicts and lists."""
    node = config if isinstance(config, DictConfig) else OmegaConf.create(config)
    value = OmegaConf.select(node, key, default=default, throw_on_resolution_failure=False)
    if OmegaConf.is_config(value):
        try:
            return OmegaConf.to_container(value, resolve=True)
        except OmegaConfBaseException:  # a value below it cannot be resolved here: as written
            return OmegaConf.to_container(value, resolve=False)
    return value
