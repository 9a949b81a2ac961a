"""Shared fixtures of the whole suite, and independent reference implementations for the SO(3) tests.

* Runs of the entry points (``python -m src.train ...``): :func:`run_train` with the tiny settings
  ``TINY`` (32 px images, lmax 2, coarse grids, a narrow network) runs in this process
  (:func:`image2sphere.testing.run_command`), so the suite pays the imports once (DDP and the joblib
  launcher still start processes); a test whose subject is the process itself (a signal, a kill) starts
  :func:`train_command` with :mod:`subprocess`.
* Session fixtures, built once and shared read-only: ``published_fixtures`` (tiny copies of every
  dataset in its published layout) and ``tiny_run`` (one epoch of the tiny default run, with its
  checkpoint, plots and TensorBoard events).
* The SO(3) references deliberately avoid the package's own code paths: they call e3nn, healpy and
  plain dense linear algebra directly.
* Parallel test processes (pytest-xdist, ``-n auto`` in pyproject.toml): one per available CPU, each with
  its share of torch's threads; the session fixtures are built once per process.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from functools import lru_cache
from pathlib import Path

import healpy
import numpy as np
import pytest
import torch
from e3nn import o3

from image2sphere.so3.wigner import default_dtype
from image2sphere.testing import run_command
from image2sphere.testing.tiny import TINY  # noqa: F401 - the tests' tiny settings, imported from here

REPO = Path(__file__).resolve().parents[1]

# smaller batches and evaluation grids than the paper's, so that a smoke run of an experiment takes seconds
SMOKE = [
    "trainer.fast_dev_run=true",
    "dataset.batch_size=4",
    "dataset.num_workers=0",
    "dataset.pin_memory=false",
    "eval_grid_level=3",
    "model.spread_grid_level=2",
    "logger=none",
]
# ------------------------------------------------------------------ parallel test processes (pytest-xdist)
MAX_WORKERS = 8  # each process holds torch, Lightning, Hydra and e3nn (about 1 GB with the session fixtures)


def pytest_xdist_auto_num_workers(config) -> int:
    """``-n auto`` (pyproject's addopts): one test process per CPU this process may run on (its affinity
    mask, which ``os.cpu_count()`` ignores in a container), at most ``MAX_WORKERS``."""
    from image2sphere.data.workers import available_cpus

    return max(1, min(available_cpus(), MAX_WORKERS))


def pytest_collection_modifyitems(config, items) -> None:
    """The longest work first, so that the parallel test processes end together. pytest-xdist's
    ``worksteal`` hands each process a contiguous share of this order and, when one runs dry, moves the
    *end* of another's share to it: a long test there runs alone at the end while the other CPUs idle
    (measured on 2 cores: a 100 s training test ran last, 80 s after the other process had finished). The
    modules with the most slow tests come first, each with its slow tests ahead of its quick ones; a
    module's tests stay together (its module-scoped fixtures are built once per process) and keep their
    order otherwise."""
    modules: dict[str, list] = {}
    for item in items:
        modules.setdefault(item.nodeid.split("::")[0], []).append(item)

    def slow(item) -> bool:
        return item.get_closest_marker("slow") is not None

    order = sorted(modules.values(), key=lambda tests: -sum(map(slow, tests)))  # stable: ties keep their order
    items[:] = [item for tests in order for item in sorted(tests, key=lambda item: not slow(item))]


def _share_the_cores() -> None:
    """In a worker of ``-n N``: torch's intra-op threads are the worker's share of the CPUs, so that N
    workers do not each start a pool as large as the machine (measured on 2 cores: the quick tier takes
    165 s with one thread per worker against 238 s with two). Processes a test starts (DDP ranks, killed
    runs) get the same number through ``OMP_NUM_THREADS`` in ``ENV``."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if os.environ.get("PYTEST_XDIST_WORKER") and workers > 1:
        from image2sphere.data.workers import available_cpus

        torch.set_num_threads(max(1, available_cpus() // workers))


_share_the_cores()


def _parse_each_config_file_once() -> None:
    """Hydra parses every YAML file of the defaults tree again at each compose (a CLI run composes twice:
    once for its mode, once to run), and the suite composes about a thousand times: a third of the quick
    tier's CPU time was composition, a quarter of that the parsing. Here each file's parse is kept per
    test process, keyed by the file's bytes (a file a test rewrites is parsed again), and every compose
    gets its own deep copy, as Hydra edits what it loaded. Without Hydra's ``FileConfigSource`` (another
    Hydra version) nothing changes."""
    import copy
    import dataclasses

    from hydra.core.plugins import Plugins

    Plugins.instance()  # Hydra's plugin scan loads its config sources' modules anew: patch the class it uses
    FileConfigSource = getattr(
        sys.modules.get("hydra._internal.core_plugins.file_config_source"), "FileConfigSource", None
    )
    if FileConfigSource is None:
        return
    parse, parsed = FileConfigSource.load_config, {}

    def load_config(self, config_path: str):
        file = os.path.realpath(os.path.join(self.path, self._normalize_file_name(config_path)))
        try:
            with open(file, "rb") as f:
                key = (self.provider, file, f.read())
        except OSError:
            return parse(self, config_path)  # Hydra's own error
        if key not in parsed:
            parsed[key] = parse(self, config_path)
        result = parsed[key]
        return dataclasses.replace(result, config=copy.deepcopy(result.config), header=dict(result.header))

    load_config.uncached = parse
    FileConfigSource.load_config = load_config


_parse_each_config_file_once()
# the environment of a run (in this process it is set for the run and restored afterwards); a run started as
# a process of its own computes with as many threads as this one, so that its numbers equal an in-process run's
ENV = {**os.environ, "WANDB_SILENT": "true", "OMP_NUM_THREADS": str(torch.get_num_threads())}


def train_command(args: list[str], data_dir: Path, log_dir: Path) -> list[str]:
    """``python -m src.train`` with ``TINY`` (the keys ``args`` set themselves left out) and the paths."""
    flags = [a for a in args if a.startswith("-")]
    overrides = [a for a in args if not a.startswith("-")]
    keys = {a.split("=")[0] for a in overrides}
    base = [a for a in TINY if a.split("=")[0] not in keys]  # args win over the tiny defaults
    paths = [f"paths.data_dir={data_dir}", f"paths.log_dir={log_dir}"]
    return [sys.executable, "-m", "src.train", *flags, *base, *paths, *overrides]


def run_module(argv: list[str], check: bool = True, env: dict | None = None, cwd: Path = REPO,
               timeout: float = 900) -> subprocess.CompletedProcess:  # fmt: skip
    """``argv`` (``[python, -m, module, ...]``) from the repository root with :func:`run_command`: in this
    process, or as a process of its own when the command starts processes itself (DDP). ``check``: a
    non-zero exit fails the test with the command's output."""
    proc = run_command(argv, cwd=cwd, env=ENV if env is None else env, timeout=timeout, extra_path=[REPO])
    if check and proc.returncode != 0:
        raise AssertionError(
            f"{' '.join(map(str, argv))} failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}"
        )
    return proc


def run_train(args: list[str], data_dir: Path, log_dir: Path, check: bool = True) -> subprocess.CompletedProcess:
    """``python -m src.train`` with the tiny settings (see :func:`train_command` and :func:`run_module`)."""
    return run_module(train_command(args, data_dir, log_dir), check=check)


def load_script(path: str) -> dict:
    """The names a script of the repository (``benchmarks/preemption.py``) defines, read without running its
    ``__main__`` block (:func:`runpy.run_path`): tests call its functions."""
    import runpy

    return runpy.run_path(str(REPO / path))


def caught(function, *args) -> BaseException:
    """What ``function(*args)`` raised (any exception, also ``SystemExit`` and ``KeyboardInterrupt``); a test
    failure when it raised nothing."""
    try:
        function(*args)
    except BaseException as e:  # noqa: BLE001 (the test looks at whatever ended it)
        return e
    raise AssertionError("nothing raised")


def read_metrics(run_dir: Path) -> dict:
    return json.loads((run_dir / "metrics.json").read_text())


@pytest.fixture(scope="session")
def published_fixtures(tmp_path_factory) -> Path:
    """Tiny copies of every dataset in its published layout (``python -m image2sphere.data.fixtures``),
    under the folder names the configs use. Shared by the whole session: never write into it."""
    from image2sphere.data.fixtures.__main__ import main

    root = tmp_path_factory.mktemp("published") / "data"
    assert main([str(root)]) == 0
    return root


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory) -> Path:
    """The run directory of one epoch of the tiny default run (``checkpoints/last.ckpt``, ``metrics.json``,
    the plots of 2 validation images and TensorBoard events); what it printed is in ``stdout.txt`` and
    ``stderr.txt`` of the directory above. Shared by the whole session: read only."""
    root = tmp_path_factory.mktemp("tiny_run")
    run = root / "run"
    plots = ["callbacks.so3_plot.every_n_epochs=1", "callbacks.so3_plot.n_images=2", "callbacks.so3_plot.level=2"]
    proc = run_train(["trainer.max_epochs=1", "logger=tensorboard", *plots, f"hydra.run.dir={run}"], root / "data",
                     root / "logs")  # fmt: skip
    assert (run / "checkpoints" / "last.ckpt").is_file() and (run / "metrics.json").is_file()
    # what the run printed, beside (not in) its directory: tests of the terminal read it
    (root / "stdout.txt").write_text(proc.stdout)
    (root / "stderr.txt").write_text(proc.stderr)
    return run


@pytest.fixture
def single_thread():
    """Run a test with one intra-op thread (restored afterwards).

    Loops of many tiny ops (e.g. ``SO3Distribution.mode(refine=True)``) slow down ~100x when torch's
    thread pool competes with other processes for the cores; one thread makes them robust.
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def haar_rotations(n: int, seed: int = 0, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Haar-random rotations from scipy (independent of ``random_rotations``)."""
    from scipy.spatial.transform import Rotation

    return torch.as_tensor(Rotation.random(n, random_state=seed).as_matrix(), dtype=dtype)


def reference_flat_wigner(lmax: int, R: torch.Tensor) -> torch.Tensor:
    """``cat_l sqrt(2l+1) * e3nn.o3.wigner_D(l, *e3nn.o3.matrix_to_angles(R)).flatten()`` in float64."""
    with default_dtype(torch.float64):
        R = R.to(torch.float64)
        angles = o3.matrix_to_angles(R)
        blocks = [math.sqrt(2 * l + 1) * o3.wigner_D(l, *angles).reshape(*R.shape[:-2], -1) for l in range(lmax + 1)]
    return torch.cat(blocks, dim=-1)


def reference_grid_angles(level: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel-major ``(alpha, beta, gamma)`` of the SO(3) HEALPix grid, straight from healpy."""
    nside = 2**level
    npix = healpy.nside2npix(nside)
    n_gamma = 6 * nside
    beta, alpha = healpy.pix2ang(nside, np.arange(npix), nest=False)
    gamma = 2 * np.pi * np.arange(n_gamma) / n_gamma
    a = np.repeat(alpha, n_gamma)
    b = np.repeat(beta, n_gamma)
    g = np.tile(gamma, npix)
    return a, b, g


def reference_grid(level: int) -> torch.Tensor:
    """Pixel-major SO(3) grid rotations in float64, built with healpy and e3nn only."""
    a, b, g = (torch.as_tensor(x, dtype=torch.float64) for x in reference_grid_angles(level))
    return o3.angles_to_matrix(a, b, g)


def brute_force_nearest(R: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """``argmax_i trace(R^T G_i)`` over the full grid (float64), for ``R`` of shape ``(M, 3, 3)``."""
    R = R.to(torch.float64).reshape(-1, 9)
    G = grid.to(torch.float64).reshape(-1, 9)
    return (R @ G.T).argmax(dim=1)


@lru_cache(maxsize=4)
def reference_dense_matrix(lmax: int, level: int) -> torch.Tensor:
    """Dense flat Wigner matrix ``(N, n_coeffs)`` of the pixel-major grid, float64, from e3nn.

    Uses ``D(alpha, beta, gamma) = D(alpha, beta, 0) @ D(0, 0, gamma)`` (a group homomorphism, tested
    in test_so3_wigner) so that level 3 stays fast.
    """
    a, b, _ = reference_grid_angles(level)
    n_gamma = 6 * 2**level
    alpha = torch.as_tensor(a[::n_gamma], dtype=torch.float64)  # [P]
    beta = torch.as_tensor(b[::n_gamma], dtype=torch.float64)  # [P]
    gamma = 2 * math.pi * torch.arange(n_gamma, dtype=torch.float64) / n_gamma  # [G]
    cols = []
    with default_dtype(torch.float64):
        for l in range(lmax + 1):
            A = o3.wigner_D(l, alpha, beta, torch.zeros_like(alpha))  # [P, d, d]
            C = o3.wigner_D(l, torch.zeros_like(gamma), torch.zeros_like(gamma), gamma)  # [G, d, d]
            D = torch.einsum("pij,gjk->pgik", A, C)  # [P, G, d, d]
            cols.append(math.sqrt(2 * l + 1) * D.reshape(len(alpha) * n_gamma, -1))
    return torch.cat(cols, dim=1)


def reference_dense_grid_logits(coeffs: torch.Tensor, lmax: int, level: int) -> torch.Tensor:
    """``coeffs @ D.T`` with the dense reference matrix, ``(B, N)`` in float64 (differentiable)."""
    return coeffs.to(torch.float64) @ reference_dense_matrix(lmax, level).T
