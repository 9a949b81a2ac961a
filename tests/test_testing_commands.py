"""``image2sphere.testing.run_command``: a command line run in this process behaves as a process of its own
(output, exit status, logging) and leaves this process as it found it. Quick (no training)."""

from __future__ import annotations

import logging
import os
import sys
import textwrap
from pathlib import Path

import pytest

from image2sphere.testing import needs_own_process, run_command

SCRIPT = """
import logging, os, sys
print("to stdout", sys.argv[1:])
print("to stderr", file=sys.stderr)
logging.getLogger("already.configured").warning("logged through a handler made before the run")
os.environ["SET_BY_THE_RUN"] = "1"
os.chdir("/")
sys.exit(int(sys.argv[1]))
"""


def test_a_script_run_in_process_gives_its_output_status_and_logs_and_leaves_no_trace(tmp_path):
    script = tmp_path / "script.py"
    script.write_text(textwrap.dedent(SCRIPT))
    logger = logging.getLogger("already.configured")
    handler = logging.StreamHandler(sys.stderr)  # as Lightning adds one at import time
    logger.addHandler(handler)
    before = (sys.argv[:], os.getcwd(), dict(os.environ), sys.path[:], handler.stream)
    try:
        proc = run_command([sys.executable, str(script), "3"], cwd=tmp_path, env={**os.environ, "X": "y"})
    finally:
        logger.removeHandler(handler)
    assert proc.returncode == 3
    assert proc.stdout == "to stdout ['3']\n"
    assert "to stderr" in proc.stderr and "logged through a handler made before the run" in proc.stderr
    assert (sys.argv, os.getcwd(), dict(os.environ), sys.path, handler.stream) == before
    assert "SET_BY_THE_RUN" not in os.environ


def test_an_uncaught_exception_is_status_1_with_its_traceback(tmp_path):
    script = tmp_path / "fails.py"
    script.write_text("raise RuntimeError('the message')\n")
    proc = run_command([sys.executable, str(script)])
    assert proc.returncode == 1
    assert "Traceback" in proc.stderr and "RuntimeError: the message" in proc.stderr


def test_a_message_given_to_sys_exit_is_status_1_on_stderr(tmp_path):
    script = tmp_path / "stops.py"
    script.write_text("import sys\nsys.exit('error: no such file')\n")
    proc = run_command([sys.executable, str(script)])
    assert (proc.returncode, proc.stderr.strip()) == (1, "error: no such file")


@pytest.mark.parametrize(
    ("args", "own"),
    [
        (["-m", "src.train"], False),
        (["-m", "src.train", "trainer=ddp"], True),
        (["-m", "src.train", "trainer.devices=2"], True),
        (["-m", "src.train", "trainer.devices=1"], False),
        (["-m", "src.train", "+trainer.strategy=ddp_spawn"], True),
        (["-m", "src.train", "-m", "hydra/launcher=local_parallel"], True),
    ],
)
def test_processes_of_their_own_for_ddp_and_the_joblib_launcher(args, own):
    assert needs_own_process(["python", *args]) is own


def test_argv_that_is_not_a_python_command_is_refused():
    with pytest.raises(ValueError, match="expected"):
        run_command(["bash", "-c", "true"])


# ------------------------------------------------------------------ which interpreter a command starts
def test_a_bare_python_in_a_process_of_its_own_is_this_interpreter(tmp_path):
    """A command that must run as a process of its own (here: a script given the joblib launcher's override)
    starts ``sys.executable`` even when its argv says ``python`` and no ``python`` is on ``PATH``."""
    script = tmp_path / "which.py"
    script.write_text("import sys\nprint(sys.executable)\n")
    argv = ["python", str(script), "hydra/launcher=local_parallel"]  # a bare python on purpose
    assert needs_own_process(argv)
    proc = run_command(argv, env={"PATH": str(tmp_path)})  # nothing to start on this PATH
    assert proc.returncode == 0 and proc.stdout.strip() == sys.executable, proc.stderr


RUNNERS = {"run", "Popen", "check_output", "check_call", "call", "system", "run_module", "run_command", "run_in"}
# where a list that starts with "python" is not a command to start: comparisons with a documented command's
# words, and the functions that only look at such a list
READERS = {"needs_own_process", "describe"}
SEARCHED = ["tests", "src/image2sphere/testing", "benchmarks"]


def bare_python_commands(source: str) -> list[int]:
    """The lines of ``source`` where a command may start whatever ``python`` is first on ``PATH``: an argv, a
    list or tuple that starts with the string ``python`` (or ``python3``) followed by ``-m``, a ``.py`` file
    or a computed value, outside a comparison and outside the arguments of :data:`READERS`; or a command
    string starting with ``python`` given to a runner. A line that says "on purpose" is left out."""
    import ast

    tree = ast.parse(source)
    parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
    purposeful = {number for number, line in enumerate(source.splitlines(), 1) if "on purpose" in line}

    def text(node) -> str | None:
        if isinstance(node, ast.JoinedStr) and node.values and isinstance(node.values[0], ast.Constant):
            node = node.values[0]
        return node.value if isinstance(node, ast.Constant) and isinstance(node.value, str) else None

    def is_argv(node) -> bool:
        if len(node.elts) < 2 or text(node.elts[0]) not in ("python", "python3"):
            return False
        second = text(node.elts[1]) if isinstance(node.elts[1], ast.Constant) else None
        return second is None or second == "-m" or second.endswith(".py")  # not a tuple of words

    def name(call: ast.Call) -> str:
        return getattr(call.func, "attr", getattr(call.func, "id", ""))

    lines = []
    for node in ast.walk(tree):
        if getattr(node, "lineno", None) in purposeful:
            continue
        if isinstance(node, (ast.List, ast.Tuple)) and is_argv(node):
            parent = parents.get(node)
            while isinstance(parent, (ast.List, ast.Tuple)):
                parent = parents.get(parent)
            if isinstance(parent, ast.Compare) or (isinstance(parent, ast.Call) and name(parent) in READERS):
                continue
            lines.append(node.lineno)
        elif isinstance(node, ast.Call) and name(node) in RUNNERS and node.args:
            command = text(node.args[0]) or ""
            if command.split(" ")[0] in ("python", "python3") and " " in command:
                lines.append(node.lineno)
    return lines


def test_the_check_finds_a_bare_python():
    found = bare_python_commands(
        "cmd = ['python', '-m', 'src.train']\n"
        "subprocess.run('python -m x', shell=True)\n"
        "os.system(f'python {script}')\n"
        "ok = words[:2] == ['python', '-m'] or needs_own_process(['python', *args])\n"
        "run_module([sys.executable, '-m', 'src.eval'])\n"
        "words = ('python', 'pip', 'git')\n"
        "Popen(('python3', script), cwd=root)\n"
    )
    assert found == [1, 2, 3, 7]


def test_tests_and_benchmarks_start_this_interpreter_never_a_bare_python():
    """Every command the tests, the testing helpers and the benchmarks start begins with ``sys.executable``: in
    a virtual environment that is not activated, ``python`` on ``PATH`` is another interpreter (without hydra)."""
    repo = Path(__file__).resolve().parents[1]
    found = {
        f"{path.relative_to(repo)}:{line}"
        for folder in SEARCHED
        for path in sorted((repo / folder).rglob("*.py"))
        for line in bare_python_commands(path.read_text())
    }
    assert not found, f"start sys.executable instead of 'python' at {sorted(found)}"
