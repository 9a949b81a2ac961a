"""Finished and unfinished runs under the directories a user names, and what each run was.

A run directory is one Hydra job's output directory: it holds ``.hydra/config.yaml``,
``.hydra/hydra.yaml`` and ``.hydra/overrides.yaml`` from the start, and ``metrics.json`` once its
test has finished (``src.train`` writes it last). A directory with ``.hydra/`` but no readable
``metrics.json`` is an *unfinished* run (still running, failed, stopped, or killed): it is reported,
never skipped in silence.

What a run was is looked up by key: a config group's choice (``model``, ``dataset``, ``experiment``,
``table``...: ``hydra.runtime.choices`` of ``.hydra/hydra.yaml``) or a dotted key of the composed
config (``lmax``, ``seed``, ``model.net.num_components``, ``dataset.shape``).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

__all__ = ["Run", "UnfinishedRun", "find_runs", "values_equal"]

_MISSING = object()


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

    def get(self, key: str, default: Any = _MISSING) -> Any:
        """A group's choice (``model``) or a dotted config value (``model.net.lmax``); ``default``
        (or ``KeyError``) when the run has neither."""
        if key in self.choices:
            return self.choices[key]
        node: Any = self.config
        for part in key.split("."):
            if not isinstance(node, dict) or part not in node:
                if default is _MISSING:
                    raise KeyError(key)
                return default
            node = node[part]
        return node

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


def _read_run(path: Path) -> Run | UnfinishedRun:
    hydra_dir = path / ".hydra"
    try:
        config = _read_yaml(hydra_dir / "config.yaml") or {}
        hydra_cfg = (_read_yaml(hydra_dir / "hydra.yaml") or {}) if (hydra_dir / "hydra.yaml").is_file() else {}
        has_overrides = (hydra_dir / "overrides.yaml").is_file()
        overrides = (_read_yaml(hydra_dir / "overrides.yaml") or []) if has_overrides else []
    except (OSError, yaml.YAMLError) as e:
        return UnfinishedRun(path, f".hydra/ is not readable ({e})")
    hydra = dict(hydra_cfg.get("hydra") or {})
    choices = dict((hydra.get("runtime") or {}).get("choices") or {})
    metrics, reason = _read_metrics(path / "metrics.json")
    if metrics is None:
        return UnfinishedRun(path, reason)
    return Run(
        path=path, metrics=metrics, choices=choices, config=config, overrides=[str(o) for o in overrides], hydra=hydra
    )


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
