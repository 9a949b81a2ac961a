"""``image2sphere.testing.run_command``: a command line run in this process behaves as a process of its own
(output, exit status, logging) and leaves this process as it found it. Quick (no training)."""

from __future__ import annotations

import logging
import os
import sys
import textwrap

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
