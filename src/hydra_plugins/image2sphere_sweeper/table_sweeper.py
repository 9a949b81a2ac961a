"""``hydra/sweeper=table``: a sweep that is a union of cartesian products, for the paper's tables.

Hydra's basic sweeper runs the cartesian product of its ``params``. A table of the paper is rarely one
product: Table 1 trains I2S with five seeds and each baseline once; Table 3 trains one model on
SYMSOL I and one per SYMSOL II shape, and only two of its methods with 10k images. This sweeper
runs the union of several products, one per entry of ``grids``::

    hydra:
      mode: MULTIRUN
      sweeper:
        params: {experiment: modelnet10}          # in every job
        grids:
          - {model: i2s, seed: "0,1,2,3,4"}         # 5 jobs
          - {model: "ipdf,matrix_fisher"}          # + 2 jobs

Each job's overrides are ``params``, then its grid's, then the command line's (a later one of the
same key wins, so ``python -m src.train table=table7 seed=3`` runs every job with seed 3, and a
sweep on the command line, ``seed=0,1``, multiplies every grid). A job that two grids both produce
runs once. ``jobs: [3, 7]`` runs only those jobs of the table (their numbers and directories are
the ones a full sweep gives them), e.g. to re-run failed ones. Jobs are launched by whatever
``hydra/launcher`` is configured (the basic one, submitit for SLURM, ...), in batches of
``max_batch_size``.
"""

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional  # noqa: UP035 (OmegaConf reads these annotations)

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.config_store import ConfigStore
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException
from omegaconf import OmegaConf

__all__ = ["TableSweeper", "TableSweeperConf", "expand_grids"]


@dataclass
class TableSweeperConf:
    _target_: str = "hydra_plugins.image2sphere_sweeper.table_sweeper.TableSweeper"
    # jobs per launch; null: all at once
    max_batch_size: Optional[int] = None  # noqa: UP045
    # overrides of every job (values may be sweeps, "a,b")
    params: Dict[str, Any] = field(default_factory=dict)  # noqa: UP006
    # the union of their cartesian products (each combined with params)
    grids: List[Dict[str, Any]] = field(default_factory=list)  # noqa: UP006
    # run only these job numbers; null: all
    jobs: Optional[List[int]] = None  # noqa: UP006, UP045


ConfigStore.instance().store(group="hydra/sweeper", name="table", node=TableSweeperConf, provider="image2sphere")


def _as_override(key: str, value: Any) -> str:
    if isinstance(value, bool):
        value = str(value).lower()
    elif value is None:
        value = "null"
    return f"{key}={value}"


def expand_grids(
    parser: OverridesParser,
    params: dict[str, Any],
    grids: Sequence[dict[str, Any]],
    arguments: Sequence[str] = (),
) -> list[list[str]]:
    """The jobs of a table: one list of ``key=value`` overrides per job, in order, duplicates dropped.

    Each grid is combined with ``params`` before it and the command line ``arguments`` after it (a
    later value of the same key replaces an earlier one), then expanded as the basic sweeper expands
    its params (a cartesian product of every swept key)."""
    jobs: list[list[str]] = []
    seen: set[tuple[str, ...]] = set()
    for grid in grids or [{}]:
        merged = [_as_override(k, v) for k, v in {**params, **grid}.items()] + list(arguments)
        overrides = parser.parse_overrides(merged)
        for job in BasicSweeper.split_arguments(overrides, None)[0]:
            key = tuple(job)
            if key not in seen:
                seen.add(key)
                jobs.append(job)
    return jobs


class TableSweeper(BasicSweeper):
    """The union of the cartesian products of ``grids`` (see the module docstring)."""

    def __init__(
        self,
        max_batch_size: int | None = None,
        params: dict[str, Any] | None = None,
        grids: Sequence[dict[str, Any]] | None = None,
        jobs: Sequence[int] | None = None,
    ) -> None:
        super().__init__(max_batch_size=max_batch_size, params=None)
        self.table_params = dict(params or {})
        self.grids = [dict(g) for g in (grids or [])]
        self.only_jobs = None if jobs is None else [int(j) for j in jobs]

    def table_jobs(self, arguments: Sequence[str]) -> list[list[str]]:
        """Every job of the table with the command line ``arguments``: its overrides, by job number."""
        assert self.hydra_context is not None
        parser = OverridesParser.create(config_loader=self.hydra_context.config_loader)
        return expand_grids(parser, self.table_params, self.grids, arguments)

    def sweep(self, arguments: list[str]) -> Any:
        assert self.config is not None and self.launcher is not None
        jobs = self.table_jobs(arguments)
        numbers = list(range(len(jobs)))
        if self.only_jobs is not None:
            bad = [j for j in self.only_jobs if not 0 <= j < len(jobs)]
            if bad:
                raise HydraException(
                    f"hydra.sweeper.jobs: job numbers {bad} do not exist; this sweep has jobs 0..{len(jobs) - 1}"
                )
            numbers = sorted(set(self.only_jobs))
        # batches of consecutive job numbers, so that each job keeps its number (and directory)
        batches: list[list[int]] = []
        size = self.max_batch_size or max(len(numbers), 1)
        for n in numbers:
            if batches and n == batches[-1][-1] + 1 and len(batches[-1]) < size:
                batches[-1].append(n)
            else:
                batches.append([n])
        self.overrides = [[jobs[n] for n in batch] for batch in batches]

        sweep_dir = Path(self.config.hydra.sweep.dir)
        sweep_dir.mkdir(parents=True, exist_ok=True)
        OmegaConf.save(self.config, sweep_dir / "multirun.yaml")
        returns = []
        for batch in batches:
            overrides = [jobs[n] for n in batch]
            self.validate_batch_is_legal(overrides)
            results = self.launcher.launch(overrides, initial_job_idx=batch[0])
            for r in results:
                _ = r.return_value  # raises the job's exception, as the basic sweeper does
            returns.append(results)
            self.batch_index += 1
        return returns
