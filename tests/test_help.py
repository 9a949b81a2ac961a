"""The ``--help`` of ``src.train``, ``src.eval`` and ``src.predict`` says what is true of ``conf/``.

Hydra's own help lists every folder under ``conf/`` as a group and dumps the composed config; each
command's ``conf/hydra/help/<command>.yaml`` replaces that with a description, examples, a pointer to
the docs, the groups a user picks from and the top-level settings. That text is written by hand (Hydra's
template has no variable for a curated listing), so these tests hold it to the files it describes:

* the groups and options listed are exactly the user-facing files of the groups the command reads
  (``src.train``: every folder under ``conf/`` and ``hydra/launcher``; ``src.eval`` and ``src.predict``:
  the groups of their own defaults list, the model coming from the checkpoint), without the internal
  files of :data:`INTERNAL`;
* an option marked ``*`` is the one the composed config chooses, and a group without a mark either has
  no default or says what decides it;
* the settings listed are the top-level keys of ``conf/<command>.yaml``, less the deprecated names of
  ``RENAMED_KEYS``, each with the default written there;
* every example composes with Hydra and passes the command's own checks of its values;
* the printed text starts with the usage line and the description, and names no internal option.

The quick tests read the text that ``--help`` prints when the entry point runs in this process
(``run_command``); one slow test runs the three commands as real processes and compares.
"""

from __future__ import annotations

import functools
import itertools
import re
import shlex
import string
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from image2sphere.testing.commands import process_group

REPO = Path(__file__).resolve().parents[1]
CONF = REPO / "conf"
COMMANDS = ("train", "eval", "predict")

# Files under conf/ that are no user's choice: a whole group, or one option as <group>/<option>.
INTERNAL = {
    # every file of the model group includes it (/module@_here_); chosen alone it adds a key nothing reads
    "module": "the LightningModule's settings, part of every model",
    # fdr, limit, overfit and profiler build on it; by itself it is one epoch of the full data, no preset
    "debug/default": "the base of the debugging presets",
}
# how each command's description starts (after its usage line and a blank line)
DESCRIPTIONS = {
    "train": "Trains a network that predicts a probability distribution over 3D rotations",
    "eval": "Tests a checkpoint written by src.train",
    "predict": "Predicts the distribution over 3D rotations of one image",
}
# the placeholders of the examples, and what stands in their place when this test composes them
PLACEHOLDERS = {"<run>": "2025-01-31_12-00-00_4242"}
WIDTH = 100  # the longest line, example commands apart (they stay whole, to be copied)


@functools.cache
def composed(command: str):
    """``conf/<command>.yaml`` composed with no overrides, the ``hydra`` section included."""
    return compose(command, [])


@functools.cache
def help_text(command: str) -> str:
    """What ``python -m src.<command> --help`` prints, rendered from the composed config as Hydra renders it
    (its ``hydra.help.template`` as a ``string.Template``, then ``print``). The template uses none of Hydra's
    variables ($APP_CONFIG_GROUPS, $CONFIG, ...): substituting nothing raises on any of them, or on a stray
    dollar sign. :func:`test_help_of_each_command_in_its_own_process` checks the real output against it."""
    return string.Template(composed(command).hydra.help.template).substitute({}) + "\n"


def section(text: str, title: str) -> list[str]:
    """The lines after the first line that starts with ``title``, up to the next empty line."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(title))
    out = []
    for line in lines[start + 1 :]:
        if not line.strip():
            break
        out.append(line)
    return out


def listed_groups(text: str) -> dict[str, tuple[str, list[str]]]:
    """``{group: (its description, [its options as printed, '*' included])}`` of the groups section: a
    group's line is indented by two spaces, its options follow on deeper-indented lines, comma-separated.
    A deeper line before the first option line continues the description."""
    groups: dict[str, tuple[str, list[str]]] = {}
    name = None
    for line in section(text, "Config groups"):
        match = re.match(r"^  (\S+)\s{2,}(\S.*)$", line)
        if match:
            name = match.group(1)
            groups[name] = (match.group(2), [])
            continue
        assert name is not None and line.startswith("    "), f"not a group or its options: {line!r}"
        description, options = groups[name]
        items = [o.strip() for o in line.split(",") if o.strip()]
        if not options and not all(re.fullmatch(r"[\w/]+\*?", o) for o in items):
            groups[name] = (f"{description} {line.strip()}", options)
        else:
            options += items
    return groups


def listed_settings(text: str) -> dict[str, str]:
    """``{key: value as printed}`` of the settings section (``  key=value   description``)."""
    out = {}
    for line in section(text, "Settings"):
        match = re.match(r"^  ([A-Za-z_]\w*)=(\S+)\s{2,}\S", line)
        assert match, f"not a setting: {line!r}"
        assert match.group(1) not in out, f"listed twice: {match.group(1)}"
        out[match.group(1)] = match.group(2)
    return out


def examples(text: str, command: str) -> list[str]:
    return [line.strip() for line in section(text, "Examples") if line.startswith(f"  python -m src.{command}")]


def read_groups(command: str) -> list[str]:
    """The groups ``src.<command>`` reads: for training every folder under conf/ (and the launcher of a
    sweep); for eval and predict the groups of their own defaults list."""
    if command == "train":
        return sorted(p.name for p in CONF.iterdir() if p.is_dir() and p.name != "hydra") + ["hydra/launcher"]
    out = []
    for entry in yaml.safe_load((CONF / f"{command}.yaml").read_text())["defaults"]:
        if isinstance(entry, dict):
            key = str(next(iter(entry)))
            if not key.startswith("override") and key != "hydra":
                out.append(key.lstrip("/"))
    return out


def user_options(group: str) -> set[str]:
    """Every file of ``conf/<group>/`` (subfolders included, as ``sub/name``) that a user may choose."""
    folder = CONF / group
    names = {p.relative_to(folder).with_suffix("").as_posix() for p in folder.rglob("*.yaml")}
    return {n for n in names if f"{group}/{n}" not in INTERNAL}


def compose(command: str, overrides: list[str]):
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from image2sphere.training import register_resolvers

    register_resolvers()
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
            return hydra_compose(config_name=command, overrides=overrides, return_hydra_config=True)
    finally:
        GlobalHydra.instance().clear()


# --------------------------------------------------------------------------------------------- the listing
@pytest.mark.parametrize("command", COMMANDS)
def test_groups_listed_are_the_user_facing_files_under_conf(command):
    groups = listed_groups(help_text(command))
    expected = {g: user_options(g) for g in read_groups(command) if g not in INTERNAL}
    assert set(groups) == set(expected), "groups listed vs. groups the command reads"
    for group, (description, options) in groups.items():
        names = [o.rstrip("*") for o in options]
        assert len(names) == len(set(names)), f"{group}: an option listed twice"
        missing, extra = sorted(expected[group] - set(names)), sorted(set(names) - expected[group])
        assert not missing and not extra, f"{group}: files not listed {missing}, listed but no file {extra}"
        assert description, group


def test_internal_files_exist_and_are_not_listed():
    """Each entry of INTERNAL names something under conf/ (else it would hide nothing), and none is listed."""
    groups = listed_groups(help_text("train"))
    for name, reason in INTERNAL.items():
        assert (CONF / name).is_dir() or (CONF / f"{name}.yaml").is_file(), f"{name} ({reason}): no such file"
        group, _, option = name.partition("/")
        listed = [o.rstrip("*") for o in groups.get(group, ("", []))[1]]
        assert name not in groups and option not in listed, f"{name} ({reason}) is listed"


@pytest.mark.parametrize("command", COMMANDS)
def test_marked_default_is_the_composed_choice(command):
    choices = composed(command).hydra.runtime.choices
    for group, (description, options) in listed_groups(help_text(command)).items():
        marked = [o.rstrip("*") for o in options if o.endswith("*")]
        assert len(marked) <= 1, group
        chosen = choices.get(group)
        if marked:
            assert chosen == marked[0], f"{group}: marked {marked[0]}, composed {chosen}"
        else:  # no default, or one the description explains (the protocol's, Hydra's own launcher)
            assert chosen is None or "default:" in description, f"{group}: composed {chosen}, nothing marked"


@pytest.mark.parametrize("command", COMMANDS)
def test_settings_are_the_top_level_keys_with_their_defaults(command):
    from image2sphere.training.run_config import RENAMED_KEYS

    stored = yaml.safe_load((CONF / f"{command}.yaml").read_text())
    stored.pop("defaults")
    for old in RENAMED_KEYS[command]:
        stored.pop(old, None)  # a deprecated name is not offered
    listed = listed_settings(help_text(command))
    assert list(listed) and set(listed) == set(stored)
    for key, shown in listed.items():
        if stored[key] == "???":  # required: a placeholder says what to give
            assert re.fullmatch(r"<[^<>]+>", shown), (key, shown)
        else:
            assert yaml.safe_load(shown) == stored[key], f"{key}: help says {shown}, conf says {stored[key]!r}"


@pytest.mark.parametrize("command", COMMANDS)
def test_examples_compose_and_pass_the_commands_checks(command):
    from hydra.core.hydra_config import HydraConfig
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from image2sphere.training.run_config import check_eval_config, check_predict_config, check_train_config

    check = {"train": check_train_config, "eval": check_eval_config, "predict": check_predict_config}[command]
    shown = examples(help_text(command), command)
    assert len(shown) == 3, shown
    for example in shown:
        for placeholder, value in PLACEHOLDERS.items():  # what a user puts in their place
            example = example.replace(placeholder, value)
        assert not re.search(r"[<>]", example), f"a placeholder this test does not fill: {example}"
        args = shlex.split(example)[3:]
        flags = [a for a in args if a.startswith("-")]
        assert set(flags) <= {"-m", "--multirun"}, example
        overrides = OverridesParser.create().parse_overrides([a for a in args if not a.startswith("-")])
        if flags:  # a sweep: each of its jobs
            keys = [o.get_key_element() for o in overrides]
            values = [list(o.sweep_string_iterator()) if o.is_sweep_override() else [o.get_value_element_as_str()]
                      for o in overrides]  # fmt: skip
            jobs = [[f"{k}={v}" for k, v in zip(keys, job, strict=True)] for job in itertools.product(*values)]
        else:
            jobs = [list(args)]
        for job in jobs:
            cfg = compose(command, job)
            HydraConfig.instance().set_config(cfg)
            try:
                check(cfg)
            finally:
                HydraConfig.instance().cfg = None


# ----------------------------------------------------------------------------------------- the printed text
@pytest.mark.parametrize("command", COMMANDS)
def test_help_starts_with_the_description_and_names_no_internal_option(command):
    from image2sphere.training.run_config import RENAMED_KEYS

    text = help_text(command)
    usage = f"python -m src.{command} "
    assert text.startswith(usage) and text.splitlines()[1] == "", text[:200]
    assert text.splitlines()[2].startswith(DESCRIPTIONS[command]), text[:400]
    assert "Examples:" in text and len(examples(text, command)) == 3
    assert "Documentation: README.md" in text and "docs/" in text
    assert f"python -m src.{command} [overrides] --cfg job" in text
    assert f"python -m src.{command} --hydra-help" in text
    assert "powered by hydra" not in text.lower() and "_target_" not in text  # neither header nor config dump
    for internal in (*INTERNAL, "pose_estimation", "experiment/fidelity", "table/small", "refine_mode"):
        assert internal not in text, internal
    for old in RENAMED_KEYS[command]:  # the deprecated names (model.refine_mode, level) are not offered
        assert not re.search(rf"(?<![\w.]){re.escape(old.rsplit('.', 1)[-1])}=", text), old
    long = [line for line in text.splitlines() if len(line) > WIDTH and not line.startswith("  python -m ")]
    assert not long, long


def test_hydra_help_stays_hydras():
    """Only the application's help is replaced: --hydra-help keeps Hydra's own template (its flags and groups)."""
    for command in COMMANDS:
        template = composed(command).hydra.hydra_help.template
        assert "$FLAGS_HELP" in template and "$HYDRA_CONFIG_GROUPS" in template, command


@pytest.mark.slow
def test_help_of_each_command_as_a_terminal_gets_it():
    """The three ``--help`` (exit status 0, nothing on stderr, the text that :func:`help_text` renders), and
    ``src.train --hydra-help`` still Hydra's. ``src.train --help`` runs as a process of its own, which imports
    neither Lightning nor the networks (``-X importtime`` lists every import on stderr); the others in this
    process (``run_command``), which the entry points treat alike."""
    from image2sphere.testing import run_command

    with process_group([sys.executable, "-X", "importtime", "-m", "src.train", "--help"], cwd=REPO,
                       stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:  # fmt: skip
        out, err = proc.communicate(timeout=300)
    imported = [line.rsplit("|", 1)[-1].strip() for line in err.splitlines() if line.startswith("import time:")]
    heavy = sorted({name.split(".")[0] for name in imported} & {"lightning", "torchmetrics", "torchvision", "e3nn"})
    assert "torch" in imported and heavy == [], heavy
    err = "".join(line + "\n" for line in err.splitlines() if not line.startswith("import time:"))
    results = {"train": (out, err, proc.returncode)}
    for name, args in {"eval": ["--help"], "predict": ["--help"], "train --hydra-help": ["--hydra-help"]}.items():
        done = run_command([sys.executable, "-m", f"src.{name.split()[0]}", *args], cwd=REPO)
        results[name] = (done.stdout, done.stderr, done.returncode)
    for name, (out, err, code) in results.items():
        assert code == 0 and err == "", f"{name}: exit status {code}\n{err}"
        if name in COMMANDS:
            assert out == help_text(name), name
        else:
            assert out.startswith("Hydra (") and "== Flags ==" in out and "--multirun" in out, out[:500]
            assert "hydra/launcher:" in out and "local_parallel" in out, out  # this project's launchers too
