"""``hydra/launcher=slurm`` on a machine without SLURM: one line on stderr, exit status 1, nothing written.

The launcher (``hydra_plugins.image2sphere_launcher.slurm_launcher``) looks for ``sbatch`` and ``srun`` on
``PATH`` before the sweep creates its directory. Each command runs from an empty working directory in
``tmp_path``: every path of a run (``paths.root_dir`` is the working directory) points there, so "nothing
written" means that directory is still empty. On a cluster (stand-in ``sbatch``/``srun`` on ``PATH``) the
sweep goes on to submitit's submission as before; tests/test_scaling.py checks the job script it writes.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ENV, REPO, run_module
from hydra_plugins.image2sphere_launcher.slurm_launcher import (
    SLURM_COMMANDS,
    check_slurm_commands,
    missing_slurm_commands,
    off_cluster_message,
)
from image2sphere.testing.commands import run_group

COMMAND = [sys.executable, "-m", "src.train", "-m", "hydra/launcher=slurm", "trainer.fast_dev_run=true"]
# the other entry points that accept a sweep (-m): the launcher stops them before their task (and its
# arguments) is looked at
SWEEPS = {
    "src.train": COMMAND,
    "src.eval": [sys.executable, "-m", "src.eval", "-m", "hydra/launcher=slurm", "ckpt_path=missing.ckpt,other.ckpt"],
    "src.predict": [
        sys.executable,
        "-m",
        "src.predict",
        "-m",
        "hydra/launcher=slurm",
        "ckpt_path=missing.ckpt",
        "image=missing.png",
    ],  # fmt: skip
}


def path_without_slurm() -> str:
    """This process's ``PATH`` without the directories that hold ``sbatch`` or ``srun``."""
    dirs = ENV.get("PATH", os.defpath).split(os.pathsep)
    return os.pathsep.join(d for d in dirs if d and not any(shutil.which(c, path=d) for c in SLURM_COMMANDS))


def fake_slurm(bin_dir: Path, commands=SLURM_COMMANDS) -> Path:
    """Stand-ins in ``bin_dir``: ``sbatch`` writes its arguments to ``bin_dir/sbatch.args`` and refuses the
    job (exit 3: the test stops at the submission), ``srun`` exits 0."""
    bin_dir.mkdir(parents=True, exist_ok=True)
    scripts = {"sbatch": f'#!/bin/sh\necho "$@" > {bin_dir / "sbatch.args"}\nexit 3\n', "srun": "#!/bin/sh\nexit 0\n"}
    for name in commands:
        (bin_dir / name).write_text(scripts[name])
        (bin_dir / name).chmod(0o755)
    return bin_dir


def off_cluster_env() -> dict[str, str]:
    return {**ENV, "PATH": path_without_slurm(), "PYTHONPATH": os.pathsep.join([str(REPO), ENV.get("PYTHONPATH", "")])}


def assert_refused(proc: subprocess.CompletedProcess, workdir: Path) -> None:
    info = f"\nstdout:\n{proc.stdout[-2000:]}\nstderr:\n{proc.stderr[-4000:]}"
    assert proc.returncode == 1, info
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, info  # the one line, no traceback, no "HYDRA_FULL_ERROR" hint
    assert "Traceback" not in proc.stderr, info
    for words in ("SLURM", "sbatch", "srun", "PATH", "hydra/launcher=local_parallel", "leave hydra/launcher out"):
        assert words in lines[0], (words, info)
    assert not list(workdir.iterdir()), f"written: {sorted(workdir.rglob('*'))}" + info  # no logs, sweep dir, .submitit


# ------------------------------------------------------------------ the check itself
def test_missing_commands_are_named(tmp_path):
    assert missing_slurm_commands(path=str(tmp_path)) == ["sbatch", "srun"]
    assert missing_slurm_commands(path=str(fake_slurm(tmp_path / "login", ["sbatch"]))) == ["srun"]
    assert missing_slurm_commands(path=str(fake_slurm(tmp_path / "cluster"))) == []
    not_executable = tmp_path / "text"
    not_executable.mkdir()
    (not_executable / "sbatch").write_text("#!/bin/sh\n")
    assert missing_slurm_commands(path=str(not_executable)) == ["sbatch", "srun"]


def test_check_exits_with_one_line_or_lets_the_launch_through(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(SystemExit) as stop:
        check_slurm_commands()
    message = stop.value.code
    assert isinstance(message, str) and "\n" not in message  # sys.exit(str): status 1, the text on stderr
    assert message == off_cluster_message(["sbatch", "srun"])
    assert "submits each job of the sweep to SLURM" in message and "no sbatch or srun on PATH" in message
    assert "hydra/launcher=local_parallel" in message and "one job after another" in message
    assert "no srun on PATH" in off_cluster_message(["srun"], launcher="my_slurm")
    assert off_cluster_message(["srun"], launcher="my_slurm").startswith("hydra/launcher=my_slurm ")
    monkeypatch.setenv("PATH", str(fake_slurm(tmp_path / "bin")))
    assert check_slurm_commands() is None


# ------------------------------------------------------------------ the commands
@pytest.mark.slow  # a process of its own: about 7 s, most of it importing torch and Lightning
def test_slurm_sweep_off_cluster_prints_one_line_and_writes_nothing(tmp_path):
    """The command as a user types it, as a process of its own: its exit status, stderr and files."""
    workdir = tmp_path / "work"
    workdir.mkdir()
    proc = run_group(COMMAND, cwd=workdir, env=off_cluster_env(), timeout=300)
    assert_refused(proc, workdir)


@pytest.mark.parametrize("module", list(SWEEPS))
def test_every_entry_point_refuses_a_slurm_sweep_off_cluster(module, tmp_path):
    """The same check in this process (quick): ``src.train``, ``src.eval`` and ``src.predict`` sweeps."""
    workdir = tmp_path / "work"
    workdir.mkdir()
    proc = run_module(SWEEPS[module], check=False, env=off_cluster_env(), cwd=workdir)
    assert_refused(proc, workdir)


def test_on_a_cluster_the_sweep_goes_on_to_submitit(tmp_path):
    """With ``sbatch`` and ``srun`` on PATH the check lets the sweep through to submitit, which writes its
    job script under the sweep's ``.submitit/`` and hands it to ``sbatch`` (the stand-in refuses the job)."""
    workdir = tmp_path / "work"
    workdir.mkdir()
    bin_dir = fake_slurm(tmp_path / "bin")
    env = {**off_cluster_env(), "PATH": f"{bin_dir}{os.pathsep}{path_without_slurm()}"}
    proc = run_module(COMMAND, check=False, env=env, cwd=workdir)
    info = f"\nstdout:\n{proc.stdout[-2000:]}\nstderr:\n{proc.stderr[-4000:]}"
    assert "on PATH (not a SLURM cluster?)" not in proc.stderr, info  # the check passed
    assert (bin_dir / "sbatch.args").is_file(), "sbatch was not called" + info
    assert proc.returncode != 0, info  # the stand-in sbatch refused the job
    (sweep,) = (workdir / "logs" / "train" / "multiruns").iterdir()
    assert (sweep / "multirun.yaml").is_file(), info
    (script,) = [Path(a) for a in (bin_dir / "sbatch.args").read_text().split() if a.endswith(".sh")]
    assert script.parent == sweep / ".submitit", (script, info)  # submitit's job script, as before
    assert "#SBATCH --signal=USR2@120" in script.read_text() and "srun" in script.read_text(), script.read_text()


# ------------------------------------------------------------------ a single run (no -m)
SINGLE = [sys.executable, "-m", "src.predict", "hydra/launcher=slurm", "ckpt_path=missing.ckpt", "image=missing.png"]


def test_a_single_run_with_the_slurm_launcher_is_not_submitted_and_says_so(tmp_path):
    """Hydra hands only a sweep's jobs to a launcher: without -m, hydra/launcher=slurm is not submitted. One
    line on stderr says so and to add -m, then the run goes on here (its own error: the image is missing), on
    a cluster or off one (where it also says that -m would stop); without a launcher there is no such line."""
    outputs = {}
    bin_dir = fake_slurm(tmp_path / "bin")
    for where, path in {"off": path_without_slurm(), "on": f"{bin_dir}{os.pathsep}{path_without_slurm()}",
                        "no launcher": path_without_slurm()}.items():  # fmt: skip
        workdir = tmp_path / where
        workdir.mkdir()
        argv = SINGLE if where != "no launcher" else [a for a in SINGLE if not a.startswith("hydra/launcher")]
        proc = run_module(argv, check=False, env={**off_cluster_env(), "PATH": path}, cwd=workdir)
        assert proc.returncode == 1 and "image not found: missing.png" in proc.stderr, proc.stderr  # it ran here
        outputs[where] = [line for line in proc.stderr.splitlines() if "hydra/launcher" in line]
    assert outputs["no launcher"] == []
    for where in ("off", "on"):
        (line,) = outputs[where]
        assert line.startswith("hydra/launcher=slurm submits the jobs of a sweep (-m) only: this single run is not "
                               "submitted to SLURM and runs here"), line  # fmt: skip
        assert "add -m" in line
    assert "add -m to submit it" in outputs["on"][0] and "PATH" not in outputs["on"][0]
    assert "no sbatch or srun on PATH, so -m would stop here" in outputs["off"][0]
    assert not (bin_dir / "sbatch.args").exists()  # nothing was submitted
