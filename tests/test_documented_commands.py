"""Every command that README.md, docs/*.md and the comments of ``conf/**/*.yaml`` show is run here, as written.

The commands are read from the documents themselves, so a changed or added command is tested without
touching this file:

* README.md and docs/*.md: every line of their ```bash blocks (trailing ``# comments`` removed), every
  inline code span that starts with a command word (``python``, ``pip``, ``wandb``, ``jupyter`` ...),
  and their ```python blocks;
* conf/**/*.yaml: comment lines of the form ``#   python -m ...`` and code spans in comments.

Optional arguments in square brackets are run when they are concrete (``[top_k=5]``) and left out when
they are placeholders (``[dataset=...]``; their names must still be config keys or groups). Identical
commands are run once. Each command runs in a scratch directory that stands in for the repository root:
``data`` and ``ROOT`` link to tiny copies of the published datasets
(``python -m image2sphere.data.fixtures``), ``logs/train/runs/<run>`` to a checkpoint trained once
here, ``benchmarks`` to this checkout's. Placeholders are filled in: ``<run>`` and ``ckpt_path=...``
(that checkpoint), ``/data/symsol`` and ``/path/to/symsol`` (``data/symsol``), image files named by
``image=`` (written here), a table's sweep directory ``logs/tableN/multiruns/<date>_<time>_<pid>`` (or
``.../<sweep>``): written here with a finished run for every job of table N, each run's ``.hydra/``
composed from the real configs as ``python -m src.train table=tableN`` composes it (on the dataset of
``--dataset`` where the command gives one) and fixed metrics. The documented arguments are never
changed or removed; the only additions (never for a key the command sets itself) are

* training: ``trainer.fast_dev_run=true`` and ``paths.*`` into the scratch directory, plus the small
  data and network settings of ``test_train_entry`` (``TINY``, ``SMOKE``) where every job's composed
  config has that key, except for the headline ``python -m src.train``, which runs its real default
  config for one batch; a resumed run gets only ``fast_dev_run``, ``logger=none`` and the paths;
* a paper table (``table=tableN``, ``hydra/sweeper=table``): ``hydra.sweeper.jobs=[0,<last>]``, its
  first and last job only (in the directories of those numbers), unless the command names its jobs;
  the keys the table itself sets get none of the small settings (``lmax=2`` would collapse Table 7);
* ``encoder.weights=IMAGENET1K_*``: torchvision cannot download here (the proxy variables point at a
  closed local port, ``TORCH_HOME`` is empty), so these runs must fail exactly at that download, for
  the weights and ResNet depth each job asks for, and not in the config. A sweep runs its jobs in
  batches and stops after the first batch with a failed job: a table's jobs 0 and last are two
  batches (the sweeper batches consecutive job numbers), so only job 0 gets to its download;
* ``python benchmarks/grid_eval.py`` (about two minutes) runs until its level-3 comparison is printed,
  ``python benchmarks/table_cost.py`` to its end (a job line for every job, a total per table),
  ``python benchmarks/projection_noise.py`` to its end (a ratio per degree), ``python benchmarks/train_step.py``
  to its end at a small size (ResNet-18, 64 px, batch 2: the paper's size takes minutes on a CPU),
  ``python benchmarks/batchnorm_statistics.py`` to its end with one timed repeat of each pass,
  ``python benchmarks/flow_grid.py`` at level 2 once (both trees give the same values),
  ``python benchmarks/preemption.py`` its schedule and command (``--dry-run``);
* ``pip install`` lines are compared with what ``.ci/run`` installs; ``python -m pytest`` is not run
  inside the suite: ``.ci/run`` must end with exactly that command;
* external tools (``SKIPPED``) are listed with the reason they are not run.

Marked slow (run by the full suite only): the benchmarks, training sweeps of more than four jobs,
commands that start processes of their own (DDP, the joblib launcher), and commands that the README
does not show (those of docs/ and config comments: variants of README commands that the quick run
covers).
"""

from __future__ import annotations

import argparse
import ast
import functools
import itertools
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import yaml
from omegaconf import open_dict
from PIL import Image

import image2sphere  # noqa: F401  (before torchvision, which check_pretrained_download imports)
from conftest import ENV, SMOKE, TINY
from image2sphere.testing import needs_own_process, run_command
from image2sphere.testing.commands import run_group
from test_table_sweeps import composed_run, table_jobs
from test_tables import make_run

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
# the Markdown documents whose commands are run: the README first, then every page of docs/
DOCUMENTS = [README, *sorted((REPO / "docs").glob("*.md"))]
CI = REPO / ".ci" / "run"

# first words of inline code spans that are commands (the rest of the README's spans are keys and values)
COMMAND_WORDS = ("python", "pip", "wandb", "jupyter", "sbatch", "srun", "bash", "sh", "git", "conda", "tensorboard")

# external tools: not run here. Keys are the command's first two words (environment assignments removed).
SKIPPED = {
    "wandb sync": "uploads an offline run to wandb.ai: needs an account and network",
    "wandb login": "stores an API key for wandb.ai: needs an account and network",
    "jupyter lab": "starts an interactive server (jupyterlab is not a dependency); tests/test_notebooks.py runs "
    "the notebooks with nbclient",
    "tensorboard --logdir": "starts a web server that runs until stopped",
}

PATH_PLACEHOLDERS = {"/data/symsol": "data/symsol", "/path/to/symsol": "data/symsol"}
# a table's sweep directory as the documents name it (its task name: tableN, or small_<x> for the table file
# small/<x>), and the directory this test writes in its place
TABLE_SWEEP = re.compile(r"logs/(table\d+|small_\w+)/multiruns/(?:<date>_<time>_<pid>|<sweep>)")
SWEEP_NAME = "2025-01-01_00-00-00_4242"
TABLE_SWEEP_DIR = re.compile(rf"logs/(table\d+|small_\w+)/multiruns/{SWEEP_NAME}")

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
PRETRAINED = re.compile(r"^encoder\.weights=(IMAGENET1K_V\d)$")
CONFIG_ERRORS = ("not in struct", "ConfigAttributeError", "Could not override", "ConfigCompositionException",
                 "MissingConfigException", "Could not find")  # fmt: skip


def table_of_task(task: str) -> str:
    """The table file (``table=...``) whose sweeps land in ``logs/<task>/``: ``small_table7`` -> ``small/table7``."""
    return task.replace("small_", "small/", 1) if task.startswith("small_") else task


# ------------------------------------------------------------------------------------------ extraction
@dataclass
class Command:
    text: str  # as documented, trailing comment removed
    where: list[str] = field(default_factory=list)  # file:line of every place that shows it


def _strip_comment(line: str) -> str:
    return re.sub(r"\s+#\s.*$", "", line).strip()


def _fenced_blocks(text: str, name: str = "README.md") -> list[tuple[str, int, list[str]]]:
    """``(language, line number of the first content line, lines)`` of every fenced block."""
    blocks, lang, start, lines = [], None, 0, []
    for number, line in enumerate(text.splitlines(), 1):
        fence = re.match(r"^\s*```\s*([\w+-]*)\s*$", line)
        if fence and lang is None:
            lang, start, lines = fence.group(1) or "text", number + 1, []
        elif fence:
            blocks.append((lang, start, lines))
            lang = None
        elif lang is not None:
            lines.append(line)
    assert lang is None, f"{name} has an unclosed code fence"
    return blocks


def _outside_fences(text: str) -> str:
    """``text`` with the lines of fenced blocks blanked (line numbers kept)."""
    out, inside = [], False
    for line in text.splitlines():
        fence = re.match(r"^\s*```", line)
        out.append("" if fence or inside else line)
        inside = inside != bool(fence)
    return "\n".join(out)


def inline_spans(text: str) -> list[tuple[int, str]]:
    """``(line, span)`` of the inline code spans outside fenced blocks (a span may wrap onto the next line)."""
    prose = _outside_fences(text)
    return [(prose.count("\n", 0, m.start()) + 1, " ".join(m.group(1).split()))
            for m in re.finditer(r"`([^`]+)`", prose) if "\n\n" not in m.group(1)]  # fmt: skip


def _first_words(text: str, n: int = 1) -> str:
    words = [w for w in text.split() if not re.match(r"^[A-Z_][A-Z0-9_]*=", w)]  # VAR=value prefixes
    return " ".join(words[:n])


def _is_command_span(span: str) -> bool:
    return _first_words(span) in COMMAND_WORDS and len(span.split()) > 1


def markdown_commands() -> list[tuple[str, str]]:
    """``(command, <document>:line)`` of every command README.md and docs/*.md show, in order."""
    found = []
    for document in DOCUMENTS:
        found += _commands_of(document.read_text(), document.relative_to(REPO).as_posix())
    return found


def _commands_of(text: str, name: str) -> list[tuple[str, str]]:
    found = []
    for lang, start, lines in _fenced_blocks(text, name):
        if lang not in ("bash", "sh", "shell", "console"):
            continue
        joined: list[tuple[int, str]] = []
        for offset, line in enumerate(lines):
            if joined and joined[-1][1].endswith("\\"):
                joined[-1] = (joined[-1][0], joined[-1][1][:-1] + " " + line.strip())
            else:
                joined.append((start + offset, line.strip()))
        for number, line in joined:
            command = _strip_comment(line)
            if command and not command.startswith("#"):
                found.append((command, f"{name}:{number}"))
    for number, span in inline_spans(text):
        if _is_command_span(span):
            found.append((span, f"{name}:{number}"))
    return found


def markdown_python_blocks() -> list[tuple[str, str]]:
    """``(code, <document>:line)`` of every ```python block of README.md and docs/*.md."""
    found = []
    for document in DOCUMENTS:
        name = document.relative_to(REPO).as_posix()
        blocks = _fenced_blocks(document.read_text(), name)
        found += [("\n".join(lines), f"{name}:{start}") for lang, start, lines in blocks if lang == "python"]
    return found


def config_commands() -> list[tuple[str, str]]:
    """``(command, file:line)`` of the commands shown in the comments of conf/**/*.yaml."""
    found = []
    for path in sorted((REPO / "conf").rglob("*.yaml")):
        where = path.relative_to(REPO).as_posix()
        for number, line in enumerate(path.read_text().splitlines(), 1):
            comment = re.match(r"^\s*#(.*)$", line)
            if not comment:
                continue
            shown = re.match(r"^\s+((?:python|pip)\s.*)$", comment.group(1))
            if shown:
                found.append((shown.group(1).strip(), f"{where}:{number}"))
            else:
                found += [(s.strip(), f"{where}:{number}") for s in re.findall(r"`([^`]+)`", comment.group(1))
                          if _is_command_span(s.strip())]  # fmt: skip
    return found


OPTIONAL = re.compile(r"(?<!\S)\[([^\[\]]*)\](?!\S)")


def expand_optional(text: str) -> tuple[str, list[str]]:
    """The command with its concrete optional arguments (``[top_k=5]`` -> ``top_k=5``) and without its
    placeholder ones (``[dataset=...]``), and the placeholder groups left out."""
    left_out: list[str] = []

    def replace(match: re.Match) -> str:
        if "..." in match.group(1):
            left_out.append(match.group(1))
            return ""
        return match.group(1)

    return " ".join(OPTIONAL.sub(replace, text).split()), left_out


def documented_commands() -> list[Command]:
    """Every distinct command (after :func:`expand_optional`) with all the places that show it."""
    commands: dict[str, Command] = {}
    for text, where in markdown_commands() + config_commands():
        key = expand_optional(text)[0]
        commands.setdefault(key, Command(key)).where.append(where)
    return list(commands.values())


COMMANDS = documented_commands()


def _placeholders_of(text: str) -> list[str]:
    for raw, _ in markdown_commands() + config_commands():
        if expand_optional(raw)[0] == text:
            yield from expand_optional(raw)[1]


def test_extraction_finds_the_documented_commands():
    texts = [c.text for c in COMMANDS]
    assert len(COMMANDS) >= 30, texts
    expected = [
        "python -m src.train",
        "python -m pytest",
        'pip install -e ".[dev,cluster]"',
        "pip install -c constraints/cpu.txt torch torchvision",
        "python -m src.train dataset=symsol2 dataset.shape=cylO",
        "python -m src.train experiment=modelnet10 encoder.weights=IMAGENET1K_V2",
        "python -m src.train -m lmax=4,6 encoder=resnet18,resnet34",
        "python -m src.train hparams_search=lmax",
        "python -m src.train ckpt_path=logs/train/runs/<run>/checkpoints/last.ckpt",
        "python -m src.eval ckpt_path=... dataset=symsol1 dataset.root=/data/symsol eval_grid_level=4 batch_size=16",
        "python -m image2sphere.data.verify symsol data/symsol",
        "python -m image2sphere.data.fixtures ROOT",
        "python benchmarks/grid_eval.py",
    ]
    for command in expected:
        assert command in texts, f"{command!r} is no longer found in the documents: {texts}"
    assert any(t.startswith("python -m src.predict ckpt_path=") for t in texts)
    assert any(t.startswith("python -m image2sphere.data.render ") for t in texts)
    assert any(t.startswith("python -m src.train -m experiment=") for t in texts)  # the paper's sweeps
    # both sources are read: the README's headline and a command that only a config comment shows
    where = {c.text: c.where for c in COMMANDS}
    assert any(w.startswith("README.md:") for w in where["python -m src.train"])
    assert any(w.startswith("conf/train.yaml:") for w in where["python -m src.train"])
    assert any(w.startswith("conf/experiment/") for t in texts for w in where[t] if "experiment=pascal3d" in t)
    # docs/ is read too
    assert any(w.startswith("docs/configuration.md:") for w in where["python -m src.train protocol=paper"])
    # no fenced block hides commands from the extractor: every bash block yields at least one
    bash_blocks = [(document.relative_to(REPO).as_posix(), block) for document in DOCUMENTS
                   for block in _fenced_blocks(document.read_text()) if block[0] == "bash"]  # fmt: skip
    assert sum(name == "README.md" for name, _ in bash_blocks) >= 10
    for name, (_, start, lines) in bash_blocks:
        assert any(w == f"{name}:{start + i}" for i in range(len(lines)) for c in COMMANDS for w in c.where), (
            f"the bash block at {name}:{start} yields no command"
        )
    assert len(markdown_python_blocks()) >= 2
    # every command word has a runner or is skipped with a reason (see test_documented_command)
    for command in COMMANDS:
        assert _first_words(command.text) in ("python", "pip") or _first_words(command.text, 2) in SKIPPED, command


def test_extraction_handles_comments_continuations_and_optional_arguments():
    assert _strip_comment("python -m src.train   # renders a set") == "python -m src.train"
    assert _strip_comment("python -m src.train dataset=symsol1") == "python -m src.train dataset=symsol1"
    text, left_out = expand_optional("python -m src.predict image=a.jpg [class_index=...] [output=plot.png]")
    assert text == "python -m src.predict image=a.jpg output=plot.png" and left_out == ["class_index=..."]
    assert expand_optional("python -m src.train dataset.shapes=[cube,cone]")[0].endswith("dataset.shapes=[cube,cone]")
    blocks = _fenced_blocks("x\n```bash\na \\\n  b\n```\n```python\nc\n```\n")
    assert blocks == [("bash", 3, ["a \\", "  b"]), ("python", 7, ["c"])]
    assert _is_command_span("I2S_CHECKPOINT=... jupyter lab notebooks/") and not _is_command_span("encoder=resnet50")
    assert _first_words("I2S_CHECKPOINT=... jupyter lab notebooks/", 2) == "jupyter lab"
    spans = inline_spans("a `python -m x\n  --y 1` b\n```bash\n`not a span`\n```\n`c`")
    assert spans == [(1, "python -m x --y 1"), (6, "c")]


def test_skip_list_holds_only_external_tools_that_are_documented():
    assert set(SKIPPED) == {"wandb sync", "wandb login", "jupyter lab", "tensorboard --logdir"}
    assert all(key.split()[0] not in ("python", "pip") for key in SKIPPED)
    shown = {_first_words(c.text, 2) for c in COMMANDS}
    assert set(SKIPPED) <= shown, f"skip entries no document shows any more: {set(SKIPPED) - shown}"


def test_placeholder_arguments_name_real_keys():
    """``[dataset=... experiment=...]``-style placeholders are left out of the runs; their names must exist."""
    groups = {p.name for p in (REPO / "conf").iterdir() if p.is_dir()}
    tops = {}
    for name in ("train", "eval", "predict"):
        tops[name] = set(yaml.safe_load((REPO / "conf" / f"{name}.yaml").read_text()))
    checked = 0
    for command in COMMANDS:
        entry = re.match(r"python -m src\.(train|eval|predict)\b", command.text)
        for group in _placeholders_of(command.text):
            for token in group.split():
                if token.endswith("=...") and token not in ("group=...", "key=..."):
                    name = token[: -len("=...")]
                    assert entry and (name in groups or name in tops[entry.group(1)]), (command.text, token)
                    checked += 1
    assert checked >= 3


# ------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def fixtures_root(published_fixtures, tmp_path_factory) -> Path:
    """A copy of the session's dataset fixtures that the commands may write into (``data/`` of the workspace:
    the built-in set rendered there, ``python -m image2sphere.data.render ... data/x``)."""
    root = tmp_path_factory.mktemp("documented") / "data"
    shutil.copytree(published_fixtures, root, symlinks=True)
    return root


@pytest.fixture(scope="module")
def checkpoint_run(tiny_run) -> Path:
    """A run directory with ``checkpoints/last.ckpt``: the session's tiny run (one epoch of the tiny default run)."""
    return tiny_run


@dataclass
class Workspace:
    root: Path  # stands in for the repository root
    run: Path  # logs/train/runs/<run> (a link to the checkpoint's run)
    env: dict

    @property
    def ckpt(self) -> str:
        return f"logs/train/runs/{self.run.name}/checkpoints/last.ckpt"


def make_workspace(root: Path, fixtures: Path, checkpoint_run: Path, with_root_link: bool = True) -> Workspace:
    root.mkdir(parents=True)
    (root / "data").symlink_to(fixtures, target_is_directory=True)
    if with_root_link:
        (root / "ROOT").symlink_to(fixtures, target_is_directory=True)
    (root / "benchmarks").symlink_to(REPO / "benchmarks", target_is_directory=True)
    runs = root / "logs" / "train" / "runs"
    runs.mkdir(parents=True)
    (runs / checkpoint_run.name).symlink_to(checkpoint_run, target_is_directory=True)
    closed = "http://127.0.0.1:9"  # nothing listens there: any download fails at once
    env = {k: v for k, v in ENV.items() if k.lower() not in ("http_proxy", "https_proxy", "no_proxy", "all_proxy")}
    env.update(
        PYTHONPATH=os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]),
        TORCH_HOME=str(root.parent / "torch_home"),
        HTTP_PROXY=closed, HTTPS_PROXY=closed, http_proxy=closed, https_proxy=closed,
        WANDB_MODE="offline", HYDRA_FULL_ERROR="0",
        # one thread: on 2 shared cores, two OpenMP threads per process made the default run 6x slower
        OMP_NUM_THREADS="1",
    )  # fmt: skip
    return Workspace(root, runs / checkpoint_run.name, env)


# ------------------------------------------------------------------------------------------ running
def override_key(arg: str) -> str:
    return arg.split("=", 1)[0].lstrip("+~")


def fill_placeholders(args: list[str], ws: Workspace) -> list[str]:
    out = []
    for arg in args:
        key, eq, value = arg.partition("=") if "=" in arg else ("", "", arg)
        if eq and key == "ckpt_path" and value == "...":
            value = ws.ckpt
        value = value.replace("logs/train/runs/<run>", f"logs/train/runs/{ws.run.name}")
        value = value.replace("<run>", f"logs/train/runs/{ws.run.name}")
        value = PATH_PLACEHOLDERS.get(value, value)
        value = TABLE_SWEEP.sub(rf"logs/\1/multiruns/{SWEEP_NAME}", value)
        out.append(f"{key}={value}" if eq else value)
    for arg in out:
        assert "<" not in arg and "..." not in arg, f"a placeholder this test does not know: {arg!r}"
    return out


def write_image(path: Path) -> None:
    import numpy as np

    pixels = np.random.default_rng(0).integers(0, 256, size=(64, 64, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(path)


def run_in(
    ws: Workspace, argv: list[str], timeout: float = 600, env: dict | None = None
) -> subprocess.CompletedProcess:
    """``argv`` from the workspace: ``python -m ...`` in this process (imports paid once per session; a
    command that starts processes itself, e.g. DDP, as a process of its own), a script as a subprocess."""
    env = ws.env if env is None else env
    if argv[1] != "-m":
        return run_group(argv, cwd=ws.root, env=env, timeout=timeout)
    return run_command(argv, cwd=ws.root, env=env, timeout=timeout, extra_path=[REPO])


def describe(argv: list[str], proc: subprocess.CompletedProcess | None = None, out: str = "", err: str = "") -> str:
    if proc is not None:
        out, err = proc.stdout, proc.stderr
    return f"\ncommand: {shlex.join(argv)}\n--- stdout (tail)\n{out[-3000:]}\n--- stderr (tail)\n{err[-5000:]}"


def table_of(args: list[str]) -> str | None:
    """The paper table a ``python -m src.train table=tableN ...`` launches (None: not a table)."""
    tables = [a.split("=", 1)[1] for a in args if "=" in a and override_key(a) == "table"]
    return tables[-1] if tables else None


def all_table_jobs(args: list[str]) -> list[list[str]]:
    """Every job of the command's table by job number, as the table sweeper expands it: the table's
    params and grids, then the command line's overrides (those not of ``hydra.``), which win."""
    arguments = [a for a in args if "=" in a and not a.startswith("-") and not override_key(a).startswith("hydra.")]
    return table_jobs(table_of(args), arguments)


def _named_jobs(args: list[str]) -> list[int] | None:
    named = [a.split("=", 1)[1] for a in args if "=" in a and override_key(a) == "hydra.sweeper.jobs"]
    return sorted({int(n) for n in yaml.safe_load(named[-1])}) if named else None


def table_selection(args: list[str]) -> list[int]:
    """The job numbers a table command runs here: those it names, or its first and last (added here)."""
    named = _named_jobs(args)
    return named if named is not None else sorted({0, len(all_table_jobs(args)) - 1})


def first_batch(numbers: list[int]) -> list[int]:
    """The table sweeper's first batch of ``numbers``: the run of consecutive numbers it starts with."""
    batch = numbers[:1]
    for n in numbers[1:]:
        if n != batch[-1] + 1:
            break
        batch.append(n)
    return batch


def sweep_values(args: list[str]) -> dict[str, list[str]]:
    """The swept keys of a multirun and their values (command-line lists, hparams_search files, and
    every key a paper table sets that the command line does not set to one value)."""
    multirun = "-m" in args or "--multirun" in args or table_of(args) is not None
    swept: dict[str, list[str]] = {}
    for arg in args:
        if arg.startswith("hparams_search="):
            conf = yaml.safe_load((REPO / "conf" / "hparams_search" / f"{arg.split('=', 1)[1]}.yaml").read_text())
            if optuna_search(args):  # distributions that Optuna samples, one job per trial
                multirun = True
                continue
            for key, values in conf["hydra"]["sweeper"]["params"].items():
                swept[key] = [str(v).strip() for v in str(values).split(",")]
            multirun = True
    if multirun:
        for arg in args:
            if "=" in arg and not arg.startswith("-") and "," in arg.split("=", 1)[1] and "[" not in arg:
                swept[override_key(arg)] = arg.split("=", 1)[1].split(",")
    if table_of(args) is not None:
        fixed = {override_key(a) for a in args if "=" in a and not a.startswith("-")} - set(swept)
        for job in all_table_jobs(args):
            for override in job:
                key, value = override_key(override), override.split("=", 1)[1]
                if key not in fixed and value not in swept.setdefault(key, []):
                    swept[key].append(value)
    return swept


def optuna_search(args: list[str]) -> bool:
    """The command runs an ``hparams_search`` file that selects Hydra's Optuna sweeper."""
    for arg in args:
        if arg.startswith("hparams_search="):
            text = (REPO / "conf" / "hparams_search" / f"{arg.split('=', 1)[1]}.yaml").read_text()
            if "override /hydra/sweeper: optuna" in text:
                return True
    return False


def job_overrides(args: list[str]) -> list[list[str]]:
    """The overrides of each job the documented command launches here (one for a single run; a table's
    selected jobs, see :func:`table_selection`)."""
    if table_of(args) is not None:
        jobs = all_table_jobs(args)
        return [jobs[n] for n in table_selection(args)]
    sweep = sweep_values(args)
    fixed = [a for a in args if "=" in a and not a.startswith("-") and override_key(a) not in sweep]
    combos = itertools.product(*[[f"{key}={v}" for v in values] for key, values in sweep.items()])
    return [fixed + list(combo) for combo in combos]


def compose_train(overrides: list[str], hydra_config: bool = False):
    """``conf/train.yaml`` composed in this process with ``overrides`` (not resolved); with ``hydra_config``
    the ``hydra`` section too (its ``runtime.choices``: the option of every group)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose(config_name="train", overrides=overrides, return_hydra_config=hydra_config)


# the modes of python -m src.train that run other code than a plain run, whatever the groups' options
MODE_KEYS = ("ckpt_path", "hparams_search", "table", "debug", "hydra.sweeper.jobs", "hydra.sweeper.n_trials")
# the groups whose option decides how a run is launched; the others choose what is trained (the model, data
# and encoder of every experiment, model and dataset are trained end to end by test_train_entry,
# test_methods_entry and test_table_sweeps). No experiment, model or dataset file chooses one of these
# (test_launch_groups_are_chosen_only_on_the_command_line_or_by_a_mode), so the command line says it all.
LAUNCH_GROUPS = ("hydra/launcher", "hydra/sweeper", "trainer", "logger")


@functools.cache
def code_path(text: str) -> tuple | None:
    """How a documented ``python -m src.train`` command runs: its modes (a sweep, a resume, a search and of
    which kind, a table, a debug setting), how it is launched (launcher, sweeper, trainer, logger),
    pretrained weights, whether it starts processes of its own, and whether it has arguments at all (the
    headline runs the real default config). Commands with the same code path differ in what they train
    (``experiment=...``, ``model=...``, ``lmax=8``), which other tests run end to end; the first of them is
    run here, the others composed and checked (:func:`check_composed_train`). None for any other command."""
    words = shlex.split(text)
    if words[:3] != ["python", "-m", "src.train"]:
        return None
    if needs_own_process(["python", *words[1:]]):  # DDP and the joblib launcher: one runs here, test_scaling
        return ("own process",)  # runs each of them (a sweep of DDP jobs, the local launcher) on its own
    args = words[3:]
    modes = tuple(sorted({override_key(a) for a in args if override_key(a) in MODE_KEYS} |
                         {a for a in args if a.startswith("-")}))  # fmt: skip
    launch = tuple(sorted(a for a in args if override_key(a) in LAUNCH_GROUPS))
    weights = any(PRETRAINED.match(a) for a in args)
    return (bool(args), modes, optuna_search(args), launch, weights)


def test_launch_groups_are_chosen_only_on_the_command_line_or_by_a_mode():
    """What :func:`code_path` assumes: only the files of the modes (``table``, ``hparams_search``, ``debug``)
    choose a launch group's option, never an experiment, model or dataset file."""
    choosers = set()
    for path in (REPO / "conf").rglob("*.yaml"):
        defaults = (yaml.safe_load(path.read_text()) or {}).get("defaults", [])
        for entry in defaults if isinstance(defaults, list) else []:
            if isinstance(entry, dict) and any(str(k).replace("override ", "").strip("/") in LAUNCH_GROUPS
                                               for k in entry):  # fmt: skip
                choosers.add(path.relative_to(REPO / "conf").parts[0])
    assert choosers and choosers <= {"table", "hparams_search", "debug", "train.yaml", "eval.yaml", "predict.yaml"}


def runs_for_real(command: Command) -> bool:
    """The first command (README first, then docs/, then config comments) of each :func:`code_path` is run;
    the others are composed and checked."""
    path = code_path(command.text)
    return path is None or next(c for c in COMMANDS if code_path(c.text) == path) is command


def check_composed_train(argv: list[str], args: list[str]) -> None:
    """A documented ``python -m src.train`` that another documented command's run covers (same code path):
    every job's config composes with the documented arguments (and this test's additions), each documented
    key and option is in it, and its values pass the run's own checks (``check_train_config``)."""
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf

    from image2sphere.training import register_resolvers
    from image2sphere.training.run_config import check_train_config

    register_resolvers()
    overrides = [a for a in args if "=" in a and not a.startswith("-")]
    additions = [a for a in argv[3 + len(args) :] if "=" in a and not override_key(a).startswith("hydra.sweeper.")]
    sweep = sweep_values(args)
    for job in job_overrides(args):
        keys = {override_key(j) for j in job}
        cfg = compose_train([*job, *[a for a in additions if override_key(a) not in keys]], hydra_config=True)
        choices = OmegaConf.to_container(cfg.hydra.runtime.choices)
        HydraConfig.instance().set_config(cfg)
        try:
            check_train_config(cfg)
        finally:
            HydraConfig.instance().cfg = None
        with open_dict(cfg):
            del cfg["hydra"]
        assert_overrides_applied(OmegaConf.to_container(cfg), choices, overrides, sweep)


def train_additions(args: list[str], ws: Workspace) -> list[str]:
    """What this test appends to a documented ``python -m src.train``: never a key the command sets, and
    the small data and network settings only where every job's config has that key (e.g. the render
    sizes only for the built-in rendered set, the I2S layer sizes not for the MLP baseline)."""
    from omegaconf import OmegaConf

    overrides = [a for a in args if "=" in a and not a.startswith("-")]
    keys = {override_key(a) for a in overrides} | set(sweep_values(args))
    paths = [f"paths.data_dir={ws.root / 'data'}", f"paths.log_dir={ws.root / 'logs'}"]
    if not overrides:  # the headline: the real default config, one batch
        return ["trainer.fast_dev_run=true", f"paths.data_dir={ws.root / 'fresh_data'}", paths[1]]
    if "ckpt_path" in keys:  # the checkpoint brings its own tiny config
        return [a for a in ["trainer.fast_dev_run=true", "logger=none", *paths] if override_key(a) not in keys]
    configs = [compose_train(job) for job in job_overrides(args)]
    out, seen = [], set(keys)
    if table_of(args) is not None and "hydra.sweeper.jobs" not in keys:  # its first and last job
        out.append(f"hydra.sweeper.jobs=[{','.join(str(n) for n in table_selection(args))}]")
    if optuna_search(args) and "hydra.sweeper.n_trials" not in keys:
        out.append("hydra.sweeper.n_trials=2")
    for arg in ["trainer.fast_dev_run=true", *SMOKE, *TINY, *paths]:
        key = override_key(arg)
        if key in seen or any(OmegaConf.select(c, key, default="<absent>", throw_on_resolution_failure=False)
                              == "<absent>" for c in configs):  # fmt: skip
            continue
        out.append(arg)
        seen.add(key)
    # a GPU command (trainer=ddp: every GPU, devices=-1) runs here on the CPU (TINY's accelerator) as 2 processes
    if "trainer.devices" not in seen and any(OmegaConf.select(c, "trainer.devices") == -1 for c in configs):
        out.append("trainer.devices=2")
    return out


def _parse_value(text: str):
    return yaml.safe_load(text) if text not in ("", "null") else None


def _select(cfg: dict, key: str):
    node = cfg
    for part in key.split("."):
        assert isinstance(node, dict) and part in node, f"{key} is not in the run's config"
        node = node[part]
    return node


def assert_overrides_applied(config: Path | dict, choices: dict, overrides: list[str], sweep: dict) -> None:
    """Each documented ``key=value`` (not swept) is in the run's config (its ``.hydra/config.yaml``, or the
    composed config), each ``group=option`` chosen."""
    cfg = config if isinstance(config, dict) else yaml.safe_load(config.read_text())
    for arg in overrides:
        key, value = override_key(arg), arg.split("=", 1)[1]
        if key in sweep or key in ("ckpt_path", "hparams_search") or key.startswith(("paths.", "hydra.")):
            continue
        if "." in key or key in cfg and not isinstance(cfg.get(key), dict):
            assert _select(cfg, key) == _parse_value(value), f"{arg}: the run used {_select(cfg, key)!r}"
        elif choices:
            assert choices.get(key) == value, f"{arg}: the run chose {key}={choices.get(key)!r}"


def _job_dirs(ws: Workspace, kind: str) -> list[Path]:
    logs = ws.root / "logs"
    if kind == "runs":
        return sorted(p for p in logs.glob("*/runs/*") if p.is_dir() and not p.is_symlink())
    return sorted(p for p in logs.glob("*/multiruns/*/*") if p.is_dir() and p.name.isdigit())


def _choices(run_dir: Path) -> dict:
    hydra_yaml = run_dir / ".hydra" / "hydra.yaml"
    return yaml.safe_load(hydra_yaml.read_text())["hydra"]["runtime"]["choices"] if hydra_yaml.is_file() else {}


def check_pretrained_download(argv, proc, args: list[str], weights: str) -> None:
    """The run composed and built its encoder, which asked torchvision for exactly ``weights``."""
    from torchvision.models import get_weight  # after image2sphere (imported above)

    info = describe(argv, proc)
    assert proc.returncode != 0, "the download cannot succeed here" + info
    for marker in CONFIG_ERRORS:
        assert marker not in proc.stderr + proc.stdout, f"a config error ({marker}), not the download" + info
    from image2sphere.training import register_resolvers

    register_resolvers()
    urls, depths = [], []
    jobs = job_overrides(args)
    if table_of(args) is not None:  # the sweep stops after its first batch (all of whose jobs fail)
        jobs = jobs[: len(first_batch(table_selection(args)))]
    for job in jobs:
        depths.append(int(compose_train(job).encoder.depth))
        urls.append(get_weight(f"ResNet{depths[-1]}_Weights.{weights}").url)
    output = proc.stdout + proc.stderr
    downloads = re.findall(r'Downloading: "([^"]+)"', output)
    assert sorted(downloads) == sorted(urls), f"expected downloads of {urls}" + info
    assert f"could not load torchvision weights ResNet{depths[0]}_Weights.{weights}" in output, info
    assert "Connection refused" in output or "urlopen error" in output, info


def test_pretrained_check_fails_on_a_config_error_or_other_weights():
    args = ["experiment=modelnet10", "encoder.weights=IMAGENET1K_V2"]
    url = "https://download.pytorch.org/models/resnet50-11ad3fa6.pth"
    download = (
        f'Downloading: "{url}" to /tmp/x\ncould not load torchvision weights ResNet50_Weights.IMAGENET1K_V2 '
        "(<urlopen error [Errno 111] Connection refused>)"
    )
    check_pretrained_download([], subprocess.CompletedProcess([], 1, "", download), args, "IMAGENET1K_V2")
    wrong_key = "Could not override 'encoder.weight'.\nKey 'weight' is not in struct"
    with pytest.raises(AssertionError, match="config error"):
        check_pretrained_download([], subprocess.CompletedProcess([], 1, "", wrong_key), args, "IMAGENET1K_V2")
    other = download.replace("resnet50-11ad3fa6", "resnet50-0676ba61").replace("V2", "V1")
    with pytest.raises(AssertionError, match="expected downloads"):
        check_pretrained_download([], subprocess.CompletedProcess([], 1, "", other), args, "IMAGENET1K_V2")


def test_a_table_command_runs_the_tables_first_and_last_job():
    """The jobs of ``table=table2``: PASCAL3D+ with ResNet-101 (not the primary config's), the command's
    keys in every job and winning over the table's; only job 0 reaches its download (two batches)."""
    from torchvision.models import get_weight

    args = ["table=table2", "encoder.weights=IMAGENET1K_V2"]
    assert table_selection(args) == [0, 15] and first_batch([0, 15]) == [0] and first_batch([3, 4, 6]) == [3, 4]
    assert table_selection([*args, "hydra.sweeper.jobs=[7,3,7]"]) == [3, 7]
    first, last = job_overrides(args)
    assert first == ["experiment=pascal3d", "model=i2s", "seed=0", *args]
    assert last == ["experiment=pascal3d", "model=rotation_flow", *args]
    assert {"experiment", "model", "seed"} <= set(sweep_values(args)) and "encoder.weights" not in sweep_values(args)
    # a key on the command line replaces the table's own sweep of it: Table 7 with lmax=4 is one job
    assert all_table_jobs(["table=table7", "lmax=4"]) == [
        ["experiment=modelnet10_limited", "model=i2s", "lmax=4", "table=table7"]
    ]
    assert "lmax" not in sweep_values(["table=table7", "lmax=4"])
    url = get_weight("ResNet101_Weights.IMAGENET1K_V2").url
    download = (f'Downloading: "{url}" to /tmp/x\ncould not load torchvision weights ResNet101_Weights.IMAGENET1K_V2 '
                "(<urlopen error [Errno 111] Connection refused>)")  # fmt: skip
    check_pretrained_download([], subprocess.CompletedProcess([], 1, "", download), args, "IMAGENET1K_V2")
    with pytest.raises(AssertionError, match="expected downloads"):  # the last job must not have run
        check_pretrained_download([], subprocess.CompletedProcess([], 1, "", download * 2), args, "IMAGENET1K_V2")


def check_train(argv, proc, args: list[str], ws: Workspace) -> None:
    info = describe(argv, proc)
    assert proc.returncode == 0, info
    overrides = [a for a in args if "=" in a and not a.startswith("-")]
    sweep = sweep_values(args)
    if table_of(args) is not None:  # the selected jobs of the table, in the directories of their numbers
        jobs, numbers, table = _job_dirs(ws, "multiruns"), table_selection(args), all_table_jobs(args)
        task = table_of(args).replace("/", "_")  # the task name: table7, small_table7 for small/table7
        assert {j.parent.parent.parent.name for j in jobs} == {task}, f"not under logs/<task>: {jobs}"
        assert sorted(int(j.name) for j in jobs) == numbers, f"job directories {jobs}, expected {numbers}" + info
        for job in jobs:
            assert (job / "metrics.json").is_file(), f"{job} has no metrics.json" + info
            ran = yaml.safe_load((job / ".hydra" / "overrides.yaml").read_text())
            missing = [o for o in table[int(job.name)] if o not in ran]
            assert not missing, f"job {job.name} of the table did not run with {missing}: {ran}" + info
            assert_overrides_applied(job / ".hydra" / "config.yaml", _choices(job), overrides, sweep)
        return
    if optuna_search(args):  # every trial ran and the best one was reported
        trials = int(next(a.split("=", 1)[1] for a in argv if override_key(a) == "hydra.sweeper.n_trials"))
        jobs = _job_dirs(ws, "multiruns")
        assert len(jobs) == trials and all((j / "metrics.json").is_file() for j in jobs), info
        (results,) = (ws.root / "logs" / "train" / "multiruns").glob("*/optimization_results.yaml")
        assert "best_value" in yaml.safe_load(results.read_text()), info
        assert (ws.root / "logs" / "optuna").is_dir(), "the study's storage was not written" + info
        return
    if sweep:
        jobs = _job_dirs(ws, "multiruns")
        expected = 1
        for values in sweep.values():
            expected *= len(values)
        assert len(jobs) == expected, f"{len(jobs)} job directories, expected {expected}" + info
        ran = set()
        for job in jobs:
            assert (job / "metrics.json").is_file(), f"{job} has no metrics.json" + info
            ran |= set(yaml.safe_load((job / ".hydra" / "overrides.yaml").read_text()))
            assert_overrides_applied(job / ".hydra" / "config.yaml", _choices(job), overrides, sweep)
        for key, values in sweep.items():
            assert {f"{key}={v}" for v in values} <= ran, f"not every value of {key} ran: {sorted(ran)}" + info
        return
    (run,) = _job_dirs(ws, "runs")
    assert (run / "metrics.json").is_file(), info
    assert not (run / "checkpoints").exists(), "fast_dev_run must not write checkpoints" + info
    assert not any((run / d).exists() for d in ("wandb", "csv", "tensorboard")), "fast_dev_run: no logger files"
    if "ckpt_path" in {override_key(a) for a in overrides}:
        assert "Resuming from" in proc.stdout + proc.stderr, info
        explicit = [a for a in overrides if override_key(a) != "ckpt_path"]
        said = re.search(r"from the command line: (.*)", proc.stdout + proc.stderr)
        for arg in explicit:  # the log says which keys came from the command line
            assert said and override_key(arg) in said.group(1).split(", "), info
        assert_overrides_applied(run / "resumed_config.yaml", {}, explicit, sweep)
    else:
        assert_overrides_applied(run / ".hydra" / "config.yaml", _choices(run), overrides, sweep)
    if not overrides:  # the README's description of the default run
        metrics = yaml.safe_load((run / "metrics.json").read_text())
        assert {"log_likelihood", "spread_deg", "acc15", "acc30", "median_error_deg"} <= set(metrics), metrics
        (rendered,) = (ws.root / "fresh_data" / "symsol_rendered").iterdir()
        assert rendered.name == "cube-cone_96px_train2400_test200_seed0_renderer1", rendered.name


def check_eval(argv, proc, args: list[str], ws: Workspace) -> None:
    info = describe(argv, proc)
    assert proc.returncode == 0, info
    (run,) = _job_dirs(ws, "runs")
    metrics = yaml.safe_load((run / "metrics.json").read_text())
    given = {override_key(a): a.split("=", 1)[1] for a in args if "=" in a}
    # not given: the level the checkpoint's run was tested at
    from image2sphere.training.checkpoint import load_checkpoint

    stored = load_checkpoint(ws.root / ws.ckpt)["run_config"]["model"]
    assert metrics["eval_grid_level"] == int(given.get("eval_grid_level", stored["eval_grid_level"])), metrics
    assert metrics["refine"] is (given.get("refine") == "true"), metrics
    assert metrics["n_images"] > 0 and (run / "metrics.md").is_file(), info
    if given.get("dataset") == "symsol1":
        assert {f"log_likelihood/{s}" for s in ("tet", "cube", "icosa", "cone", "cyl")} <= set(metrics), metrics
    overrides = [a for a in args if override_key(a) != "ckpt_path"]
    assert_overrides_applied(run / ".hydra" / "config.yaml", _choices(run), overrides, {})


def check_predict(argv, proc, args: list[str], ws: Workspace) -> None:
    info = describe(argv, proc)
    assert proc.returncode == 0, info
    given = {override_key(a): a.split("=", 1)[1] for a in args if "=" in a}
    assert "mode 1: mass" in proc.stdout or "no modes" in proc.stdout, info
    image = Path(given["image"])
    plot = ws.root / given.get("output", str(image.with_name(f"{image.stem}_so3.png")))
    assert plot.is_file() and plot.stat().st_size > 1000, f"no plot at {plot}" + info
    if "top_k" in given and "mode 1: mass" in proc.stdout:
        assert len(re.findall(r"^mode \d+: mass", proc.stdout, re.M)) <= int(given["top_k"])


def check_verify(argv, proc, args: list[str], ws: Workspace) -> None:
    """The fixtures are complete and readable but far smaller than the releases: only counts may differ."""
    info = describe(argv, proc)
    assert proc.returncode in (0, 1), info
    assert " at data/" in proc.stdout and "Traceback" not in proc.stderr, info
    assert "problems:" not in proc.stdout and "unreadable files:" not in proc.stdout, info
    rows = re.findall(r"^  (\S.*?)\s+(\d+)\s+(\d+|-)(  <-- mismatch)?$", proc.stdout, re.M)
    # every class the release has images of is found in the copy (only the numbers differ)
    assert rows and all(int(found) > 0 for _, found, expected, _ in rows if expected not in ("-", "0")), info
    assert (proc.returncode == 1) == any(flag for *_, flag in rows), info
    if "--synthetic" in args:
        assert "synthetic images/" in proc.stdout, info


def check_preemption(argv, proc, args: list[str], ws: Workspace) -> None:
    """The pre-emption stress check (``benchmarks/preemption.py``) takes about 25 minutes: here its schedule
    (``--dry-run``, added); its moments run for real in test_scaling (the hardest two) and as the script itself."""
    assert proc.returncode == 0, describe(argv, proc)
    lines = [line.split() for line in proc.stdout.splitlines() if line[:2].strip().isdigit()]
    assert len(lines) == 22 and {w[2] for w in lines} == {"rank0", "group"}, proc.stdout
    command = proc.stdout.splitlines()[0].split()
    assert command[:2] == ["-m", "src.train"] and {"trainer=ddp", "trainer.devices=2"} <= set(command), proc.stdout


def check_folder_axes(argv, proc, args: list[str], ws: Workspace) -> None:
    """``python -m image2sphere.data.folder <folder> --out <png>``: the picture of the labels' axes is written."""
    assert proc.returncode == 0 and proc.stdout.startswith("wrote "), describe(argv, proc)
    out = ws.root / args[args.index("--out") + 1]
    assert out.read_bytes()[:4] == b"\x89PNG", describe(argv, proc)


def check_fixtures(argv, proc, args: list[str], ws: Workspace) -> None:
    assert proc.returncode == 0, describe(argv, proc)
    root = ws.root / args[-1]
    names = {"symsol", "ModelNet10-SO3", "PASCAL3D+_release1.1", "syn_images_cropped_bkg_overlaid", "my_poses"}
    assert {p.name for p in root.iterdir()} == names, describe(argv, proc)


def check_render(argv, proc, args: list[str], ws: Workspace) -> None:
    import numpy as np

    from image2sphere.data.render import _build_parser

    assert proc.returncode == 0, describe(argv, proc)
    if "--help" in args:  # the options listed, nothing written
        assert proc.stdout.startswith("usage:") and "--image-size" in proc.stdout, describe(argv, proc)
        return
    options = _build_parser().parse_args(args[2:])  # what the documented arguments ask for
    root = ws.root / options.root
    for split in ("train", "test"):
        with np.load(root / split / "rotations.npz", allow_pickle=False) as npz:
            assert sorted(npz.files) == sorted(options.shapes)
        images = sorted((root / split / "images").glob("*.png"))
        assert len(images) == getattr(options, split) * len(options.shapes), (split, len(images))
        assert Image.open(images[0]).size == (options.image_size, options.image_size)


def check_benchmark(argv, ws: Workspace, seconds: float = 120) -> None:
    """Runs the documented benchmark until its level-3 comparison is complete (or it ends): it must pass."""
    env = {**ws.env, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(argv, cwd=ws.root, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)  # fmt: skip
    lines: list[str] = []
    timer = threading.Timer(seconds, os.killpg, (proc.pid, signal.SIGKILL))
    timer.start()
    try:
        for line in proc.stdout:
            lines.append(line)
            if line.startswith("=== level 4"):  # level 3 is complete: enough to know the command works
                break
    finally:
        timer.cancel()
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)  # the benchmark and its peak-RSS children
        proc.wait()
    out = "".join(lines)
    info = describe(argv, out=out)
    assert "Traceback" not in out and "FAIL" not in out, info
    assert "=== level 3:" in out and "check argmax: 64/64" in out, info
    if "=== level 4" not in out:  # it ended before level 4 (other levels asked for): it must have succeeded
        assert proc.returncode == 0 and "total benchmark time" in out, info


def test_benchmark_command_line_parses():
    proc = subprocess.run([sys.executable, "benchmarks/grid_eval.py", "--help"], cwd=REPO, capture_output=True,
                          text=True, timeout=120)  # fmt: skip
    assert proc.returncode == 0 and "--levels" in proc.stdout and "--dense-level5" in proc.stdout, proc.stderr


def check_table_cost(argv, ws: Workspace) -> None:
    """``benchmarks/table_cost.py`` to its end: a line for every job of each table asked for, and a total."""
    options = argparse.ArgumentParser(add_help=False)
    options.add_argument("--tables", default=",".join(sorted(p.stem for p in (REPO / "conf" / "table").glob("*.yaml"))))
    tables = options.parse_known_args(argv[2:])[0].tables.split(",")
    proc = run_in(ws, argv, timeout=1800)
    info = describe(argv, proc)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, info
    lines = proc.stdout.splitlines()
    for table in tables:
        jobs = table_jobs(table)
        assert f"## {table}: {len(jobs)} jobs" in lines, info
        section = lines[lines.index(f"## {table}: {len(jobs)} jobs") + 1 :]
        for job in jobs:
            assert any(re.match(rf"{re.escape(' '.join(job))}\s+\d", line) for line in section), (job, info)
        total = next((line for line in section if line.startswith("total:")), "")
        assert "GPU-hours (estimate)" in total and "CPU-hours" in total, info


def write_table_sweep(sweep: Path, table: str, dataset: str | None) -> None:
    """A finished run for every job of ``table`` under ``sweep`` (``<sweep>/<job number>``), as
    ``python -m src.train table=<table> [dataset=<dataset>]`` leaves them, with fixed metrics for every
    metric any table's layout reads."""
    from image2sphere.reporting import load_layouts

    metrics = {"n_images": 100.0}
    for layout in load_layouts().values():
        for name in filter(None, (column.get("metric") for column in layout["columns"])):  # not the mean_of ones
            metrics[name] = 0.5 if name.startswith("acc") else 3.0 if name.startswith("log_likelihood") else 20.0
    arguments = [f"dataset={dataset}"] if dataset else []
    for number, job in enumerate(table_jobs(table, arguments)):
        run = composed_run(table, job, number)
        make_run(sweep, str(number), run.choices, run.config, metrics, [f"table={table}", *job])


def tables_options(args: list[str]) -> argparse.Namespace:
    """The run directories and the options of a ``python -m src.tables`` command that this test reads."""
    options = argparse.ArgumentParser(add_help=False)
    options.add_argument("run_dirs", nargs="*")
    options.add_argument("--table", action="append")
    options.add_argument("--dataset")
    options.add_argument("--out", type=Path)
    return options.parse_known_args(args)[0]


def check_tables(argv, proc, args: list[str], ws: Workspace) -> None:
    """``python -m src.tables <sweep> ...``: the table printed with our runs in it, and written."""
    info = describe(argv, proc)
    assert proc.returncode == 0, info
    if "--help" in args or "-h" in args:
        assert proc.stdout.startswith("usage:") and "RUN_DIR" in proc.stdout and "--table" in proc.stdout, info
        return
    from image2sphere.reporting import load_layouts

    given = tables_options(args)
    tables = given.table or sorted({m.group(1) for d in given.run_dirs for m in [TABLE_SWEEP_DIR.search(d)] if m})
    assert tables, f"no table named or launched: {args}"
    out = ws.root / (given.out or Path(given.run_dirs[0]) / "tables")
    for table in tables:
        number = re.fullmatch(r"table(\d+)", table)  # a paper's table, else a small sweep's own layout
        heading = f"### Table {number.group(1)}" if number else f"### {load_layouts()[table]['title']}"
        assert heading in proc.stdout, info
        assert (out / f"{table}.md").is_file() and (out / f"{table}.tex").is_file(), f"nothing written to {out}" + info
    assert "ours (" in proc.stdout, "no row has a run" + info
    assert "not in this table" not in proc.stdout and "not finished" not in proc.stdout + proc.stderr, info
    if given.dataset:  # runs on other data than the paper's: the table says so
        assert "not comparable" in proc.stdout, info


SBATCH_OPTIONS = {"partition": "--partition={}", "nodes": "--nodes={}", "gpus_per_node": "--gpus-per-node={}",
                  "account": "--account={}", "timeout_min": "--time={}", "mem_gb": "--mem={}GB"}  # fmt: skip


def check_slurm_submission(argv: list[str], args: list[str], ws: Workspace) -> None:
    """A ``hydra/launcher=slurm`` command submits to a stand-in ``sbatch`` (no cluster here), which keeps the
    job script and refuses the job: the script asks SLURM for what the command says, one task per GPU and
    an array of one job per run."""
    bin_dir = ws.root / "slurm_bin"
    bin_dir.mkdir()
    keep = f'for a in "$@"; do cp "$a" {ws.root}/job.sh 2>/dev/null; done'
    (bin_dir / "sbatch").write_text(f"#!/bin/sh\n{keep}\nexit 3\n")
    (bin_dir / "srun").write_text("#!/bin/sh\nexit 0\n")
    for tool in ("sbatch", "srun"):
        (bin_dir / tool).chmod(0o755)
    env = {**ws.env, "PATH": f"{bin_dir}{os.pathsep}{ws.env['PATH']}"}
    proc = run_in(ws, argv, timeout=300, env=env)
    info = describe(argv, proc)
    assert (ws.root / "job.sh").is_file(), "nothing was submitted" + info
    script = (ws.root / "job.sh").read_text()
    given = {override_key(a): a.split("=", 1)[1] for a in args if "=" in a}
    for key, option in SBATCH_OPTIONS.items():
        if f"hydra.launcher.{key}" in given:
            assert f"#SBATCH {option.format(given[f'hydra.launcher.{key}'])}" in script, (option, script)
    gpus = given.get("hydra.launcher.gpus_per_node", "1")
    assert f"#SBATCH --ntasks-per-node={gpus}" in script, script
    assert given.get("trainer.devices", gpus) == gpus and "--signal=USR2@" in script, script
    jobs = len(job_overrides(args))
    assert re.search(rf"#SBATCH --array=0-{jobs - 1}%\d+", script), (jobs, script)


def check_pip(command: str) -> None:
    """A README ``pip install`` line installs what ``.ci/run`` installs (same packages, same pins)."""

    def tokens(line: str) -> list[str]:
        words = shlex.split(line)
        return words[2:] if words[:2] == ["python", "-m"] else words

    ci = [tokens(line) for line in CI.read_text().splitlines() if "pip install" in line and not line.startswith("#")]
    assert tokens(command) in ci, f"{command!r} is not what .ci/run installs: {ci}"
    words = tokens(command)
    for flag, value in zip(words, words[1:], strict=False):  # a constraints file: it exists and pins what it names
        if flag in ("-c", "--constraint"):
            pinned = [ln.split("==")[0].strip() for ln in (REPO / value).read_text().splitlines() if "==" in ln]
            named = [w for w in words if not w.startswith("-") and w not in ("pip", "install", value)]
            assert set(named) <= set(pinned) or "-e" in words, f"{value} does not pin {named}"


def check_pytest(command: str) -> None:
    lines = [ln.strip() for ln in CI.read_text().splitlines() if ln.strip() and not ln.strip().startswith("#")]
    assert lines[-1] == command, f".ci/run ends with {lines[-1]!r}, not the README's test command {command!r}"


def check_pytest_tier(args: list[str]) -> None:
    """``python -m pytest -m EXPR``: the expression parses and names only markers registered in pyproject.toml
    (an unknown one would select every test, or none, without a word)."""
    import tomllib
    from _pytest.mark.expression import Expression

    assert len(args) == 2 and args[0] == "-m", f"a documented tier must be 'python -m pytest -m EXPR', got {args}"
    registered = {m.split(":")[0].strip() for m in tomllib.loads((REPO / "pyproject.toml").read_text())["tool"][
        "pytest"]["ini_options"]["markers"]}  # fmt: skip
    named = set(re.findall(r"[A-Za-z_][A-Za-z0-9_]*", args[1])) - {"and", "or", "not"}
    Expression.compile(args[1])
    assert named and named <= registered, f"{args[1]!r} names {named - registered}, not markers of pyproject.toml"


def render_documented_sets(args: list[str], ws: Workspace) -> None:
    """A documented training run on a set that a documented render command writes (``dataset.root=data/x``):
    that render command runs first, as the documents say (it does nothing when the set is already there)."""
    for arg in args:
        key, _, value = arg.partition("=")
        if key != "dataset.root" or not value.startswith("data/") or (ws.root / value).exists():
            continue
        renders = [c.text for c in COMMANDS if shlex.split(c.text)[1:4] == ["-m", "image2sphere.data.render", value]]
        assert renders, f"{value} is neither a fixture nor written by a documented render command"
        argv = [sys.executable, *shlex.split(renders[0])[1:]]
        proc = run_in(ws, argv)
        assert proc.returncode == 0, describe(argv, proc)


def _param(command: Command):
    """A parametrized case. Slow: the benchmarks, training sweeps of more than four jobs (a table runs
    two unless it names its jobs), commands that start processes of their own (DDP), and commands that
    the README does not show (docs/ and config comments: variants of the README's, which the quick run
    covers)."""
    words = shlex.split(command.text)
    if not runs_for_real(command):  # composed and checked only: quick
        return pytest.param(command, id=command.text)
    slow = words[0] == "python" and len(words) > 1 and words[1].startswith("benchmarks/")  # every benchmark
    slow = slow or not any(w.startswith("README.md:") for w in command.where) and _first_words(command.text) == "python"
    slow = slow or needs_own_process(words)  # DDP and the joblib launcher: processes of their own
    if words[:3] == ["python", "-m", "src.train"] and not any(PRETRAINED.match(w) for w in words):
        if table_of(words[3:]) is not None:  # its first and last job, unless it names its jobs
            slow = slow or len(_named_jobs(words[3:]) or [0, 1]) > 4
        else:
            slow = slow or len(job_overrides(words[3:])) > 4
    return pytest.param(command, id=command.text, marks=[pytest.mark.slow] if slow else [])


@pytest.mark.parametrize("command", [_param(c) for c in COMMANDS])
def test_documented_command(command: Command, fixtures_root, checkpoint_run, tmp_path):
    text = command.text
    skip = SKIPPED.get(_first_words(text, 2))
    if skip:
        pytest.skip(f"not run: {skip}")
    words = shlex.split(text)
    if words[:2] == ["pip", "install"]:
        return check_pip(text)
    if words == ["python", "-m", "pytest"]:
        return check_pytest(text)
    if words[:3] == ["python", "-m", "pytest"]:  # a tier of the suite: not run inside the suite itself
        return check_pytest_tier(words[3:])
    assert words[0] == "python", f"no runner for {text!r} (shown at {command.where})"
    fixtures_cmd = words[1:3] == ["-m", "image2sphere.data.fixtures"]
    ws = make_workspace(tmp_path / "repo", fixtures_root, checkpoint_run, with_root_link=not fixtures_cmd)
    args = fill_placeholders(words[1:], ws)
    for arg in args:
        if arg.startswith("image=") and not (ws.root / arg.split("=", 1)[1]).exists():
            write_image(ws.root / arg.split("=", 1)[1])
    argv = [sys.executable, *args]
    if args[0] == "benchmarks/grid_eval.py":
        return check_benchmark(argv, ws)
    if args[0] == "benchmarks/table_cost.py":
        return check_table_cost(argv, ws)
    if args[0] == "benchmarks/data.py":  # every reader on the fixtures and the model's step, to the end
        proc = run_in(ws, argv, timeout=300)
        assert proc.returncode == 0 and "total benchmark time" in proc.stdout, describe(argv, proc)
        readers = {"symsol", "modelnet10", "pascal3d", "symsol_rendered"}
        assert readers <= {line.split()[0] for line in proc.stdout.splitlines() if line.strip()}, proc.stdout
        return
    if args[0] == "benchmarks/train_step.py":  # the paper's size is minutes on a CPU: the same script, small
        small = ["--batch", "2", "--image-size", "64", "--encoder", "resnet18", "--repeats", "1", "--warmup", "1",
                 "--eval-batch", "1", "--level", "3"]  # fmt: skip
        proc = run_in(ws, [*argv, *small], timeout=600)
        out = proc.stdout
        assert proc.returncode == 0 and "bf16 / float32 step time:" in out, describe(argv, proc)
        assert "training step, float32" in out and "level-3 evaluation" in out, out
        assert "training step, float32 unfused" in out and "fused / unfused optimiser:" in out, out
        return
    if args[0] == "benchmarks/flow_grid.py":  # both trees at level 2, once: the ratios and the same values
        small = ["--level", "2", "--eval-level", "2", "--spread-level", "2", "--repeats", "1", "--batch", "4"]
        proc = run_in(ws, [*argv, *small], timeout=600)
        assert proc.returncode == 0 and "flow test batch" in proc.stdout, describe(argv, proc)
        differences = re.findall(r"largest difference of .*: (\S+)", proc.stdout)
        assert len(differences) == 3 and all(float(d) < 1e-4 for d in differences), proc.stdout
        return
    if args[0] == "benchmarks/batchnorm_statistics.py":  # to the end, one timed repeat of each
        proc = run_in(ws, [*argv, "--repeats", "1", "--warmup", "1"], timeout=600)
        assert proc.returncode == 0 and "statistics pass (one batch):" in proc.stdout, describe(argv, proc)
        assert re.search(r"\+\d+% of the epoch's training steps", proc.stdout), proc.stdout
        return
    if args[0] == "benchmarks/projection_noise.py":  # to the end: a ratio for every degree and image size
        proc = run_in(ws, argv, timeout=600)
        assert proc.returncode == 0 and "measured in" in proc.stdout, describe(argv, proc)
        rows = [line.split() for line in proc.stdout.splitlines() if line[:1].isdigit()]
        assert [int(r[0]) for r in rows] == list(range(len(rows))) and len(rows) >= 3, proc.stdout
        assert all(float(v) > 0 for r in rows for v in r[1:]), proc.stdout
        return
    if args[0] == "benchmarks/relu_grid.py":  # to the end: both ReLUs of every band limit, the same numbers
        proc = run_in(ws, argv, timeout=600)
        assert proc.returncode == 0 and "total benchmark time" in proc.stdout, describe(argv, proc)
        rows = [r for r in (line.split() for line in proc.stdout.splitlines()) if r and r[0].isdigit()]
        assert [int(r[0]) for r in rows] == [4, 6], proc.stdout
        assert all(float(r[8]) < 1e-12 for r in rows), proc.stdout  # float64: e3nn's numbers
        assert all(float(r[7]) < float(r[6]) for r in rows), proc.stdout  # less memory than e3nn's dense grids
        assert proc.stdout.count("ratios e3nn / ours") == 2, proc.stdout
        return
    if args[0] == "benchmarks/preemption.py":  # its schedule and command (the moments: test_scaling)
        argv += ["--dry-run"]
        return check_preemption(argv, run_in(ws, argv), args, ws)
    assert args[0] == "-m", f"no runner for {text!r}"
    module, rest = args[1], args[2:]
    if module == "src.train":
        weights = [PRETRAINED.match(a).group(1) for a in rest if PRETRAINED.match(a)]
        argv += train_additions(rest, ws)
        if not runs_for_real(command):
            return check_composed_train(argv, rest)
        if "hydra/launcher=slurm" in rest:
            return check_slurm_submission(argv, rest, ws)
        render_documented_sets(rest, ws)
        proc = run_in(ws, argv)
        if weights:
            return check_pretrained_download(argv, proc, rest, weights[0])
        return check_train(argv, proc, rest, ws)
    checks = {
        "src.eval": check_eval,
        "src.predict": check_predict,
        "image2sphere.data.verify": check_verify,
        "image2sphere.data.fixtures": check_fixtures,
        "image2sphere.data.folder": check_folder_axes,
        "image2sphere.data.render": check_render,
        "src.tables": check_tables,
    }
    assert module in checks, f"no runner for python -m {module} (shown at {command.where})"
    if module in ("src.eval", "src.predict"):
        argv += [f"paths.log_dir={ws.root / 'logs'}"]
    if module == "src.tables":  # the sweeps it reads: a finished run for every job of the table
        given = tables_options(rest)
        for run_dir in given.run_dirs:
            sweep = TABLE_SWEEP_DIR.fullmatch(run_dir)
            if sweep and not (ws.root / run_dir).exists():
                write_table_sweep(ws.root / run_dir, table_of_task(sweep.group(1)), given.dataset)
    proc = run_in(ws, argv)
    checks[module](argv, proc, rest if module.startswith("src.") else args, ws)


# ------------------------------------------------------------------------------------------ python blocks
CLAIM = re.compile(r"^(?P<code>.*?\S)\s+#\s*(?P<claim>\[[\d,\s]+\]|[A-Z]\w+)")


def _is_claim(claim: str) -> bool:
    """A shape, or the name of one of the package's public classes."""
    import image2sphere.distributions
    import image2sphere.inference
    import image2sphere.nn
    import image2sphere.so3

    modules = (image2sphere.so3, image2sphere.distributions, image2sphere.nn, image2sphere.inference)
    return claim.startswith("[") or any(isinstance(getattr(m, claim, None), type) for m in modules)


ASSIGN = re.compile(r"^(?P<indent>\s*)(?P<name>[A-Za-z_]\w*)\s*=(?!=)")


def with_claim_checks(code: str) -> tuple[str, int]:
    """``code`` with the shape (``# [2, 455] ...``) or type (``# SO3Distribution ...``) its comments claim
    asserted after each such line; and the number of claims."""
    lines, claims = [], 0
    for number, line in enumerate(code.splitlines(), 1):
        match = CLAIM.match(line)
        if not match or not _is_claim(match.group("claim")):
            lines.append(line)
            continue
        claims += 1
        stripped, claim = match.group("code"), match.group("claim")
        assign = ASSIGN.match(stripped)
        if assign:
            lines += [stripped, f"{assign.group('indent')}_claim({assign.group('name')}, {claim!r}, {number})"]
        else:
            indent = stripped[: len(stripped) - len(stripped.lstrip())]
            lines.append(f"{indent}_claim({stripped.strip()}, {claim!r}, {number})")
    header = (
        "_checked = []\n"
        "def _claim(value, claim, line):\n"
        "    if claim.startswith('['):\n"
        "        shape = [int(x) for x in claim.strip('[]').split(',')]\n"
        "        assert list(value.shape) == shape, f'line {line}: shape {list(value.shape)}, documented {shape}'\n"
        "    else:\n"
        "        assert type(value).__name__ == claim, f'line {line}: a {type(value).__name__}, documented {claim}'\n"
        "    _checked.append(line)\n"
    )
    footer = "\nprint('CLAIMS CHECKED', len(_checked))\n"
    return header + "\n".join(lines) + footer, claims


def test_claim_checks_can_fail():
    code, claims = with_claim_checks("import torch\nx = torch.zeros(2, 3)  # [2, 4] wrong\n")
    assert claims == 1
    with pytest.raises(AssertionError, match="documented"):
        exec(compile(code, "<claims>", "exec"), {})


@pytest.mark.parametrize(
    "block", [pytest.param(b, id=where, marks=[] if where.startswith("README.md:") else [pytest.mark.slow])
              for b, where in markdown_python_blocks()]
)  # fmt: skip
def test_markdown_python_block(block, fixtures_root, checkpoint_run, tmp_path):
    ws = make_workspace(tmp_path / "repo", fixtures_root, checkpoint_run)
    block = block.replace("logs/train/runs/<run>", f"logs/train/runs/{ws.run.name}")
    for node in ast.walk(ast.parse(block)):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value.endswith(IMAGE_SUFFIXES):
            write_image(ws.root / node.value)
    assert "<" not in re.sub(r"#.*", "", block), f"a placeholder this test does not know:\n{block}"
    code, claims = with_claim_checks(block)
    script = ws.root / "documented_block.py"
    script.write_text(code)
    argv = [sys.executable, str(script)]
    proc = run_command(argv, cwd=ws.root, env=ws.env, extra_path=[REPO])  # in this process: imports paid once
    assert proc.returncode == 0, describe(["python", "<documented block>"], proc) + "\n" + code
    assert f"CLAIMS CHECKED {claims}" in proc.stdout, proc.stdout
