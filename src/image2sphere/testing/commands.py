"""Run a ``python -m <module> ...`` or ``python <script> ...`` command line in this process.

A test of a command line (``python -m src.train trainer.fast_dev_run=true``) spends most of its time
starting a Python process and importing torch, Lightning, Hydra and e3nn. :func:`run_command` runs the
same module as ``__main__`` with the same arguments, working directory and environment inside the
calling process and returns what :func:`subprocess.run` would (exit status, stdout, stderr), so that
the imports are paid once per test session. What differs from a real process is undone afterwards:
``sys.argv``, ``sys.path``, the environment, the working directory, the root logger's handlers, the
warning filters and Hydra's global state.

What cannot be run in-process is run as a subprocess (:func:`needs_own_process`): a command that starts
more processes from its own command line (Lightning's DDP on several devices re-executes
``sys.argv``; Hydra's joblib launcher). A command a test means to signal or kill is started with
:mod:`subprocess` by the test itself.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import runpy
import signal
import subprocess
import sys
import warnings
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

__all__ = ["group_alive", "needs_own_process", "process_group", "run_command", "run_group"]

# overrides after which a run starts other processes from its own command line
_OWN_PROCESS = ("trainer=ddp", "hydra/launcher=local_parallel")


def needs_own_process(argv: Sequence[str]) -> bool:
    """Whether ``argv`` (``[python, -m, module, *args]``) must run as a process of its own.

    True for DDP on more than one device (Lightning re-executes the command line once per device)
    and for Hydra's joblib launcher (its workers import the task function from ``__main__``).
    """
    args = list(argv[1:])
    if any(a in _OWN_PROCESS for a in args):
        return True
    for arg in args:
        key, _, value = arg.partition("=")
        if key.lstrip("+") == "trainer.devices" and value not in ("1", "auto", "null", "[0]"):
            return True
        if key.lstrip("+") == "trainer.strategy" and value.startswith("ddp"):
            return True
    return False


def run_command(
    argv: Sequence[str],
    cwd: str | os.PathLike | None = None,
    env: Mapping[str, str] | None = None,
    timeout: float | None = None,
    extra_path: Sequence[str | os.PathLike] = (),
) -> subprocess.CompletedProcess:
    """Run ``argv`` (``[sys.executable, "-m", module, *args]`` or ``[sys.executable, script, *args]``).

    In this process unless :func:`needs_own_process` says otherwise, in which case it is
    :func:`run_group` (``subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True,
    timeout=timeout)`` in a process group that is ended whatever happens), with a bare
    ``python`` or ``python3`` as ``argv[0]`` replaced by ``sys.executable`` (the interpreter that runs the
    in-process case too; the ``python`` first on ``PATH`` may be another one, e.g. in a virtual environment
    that is not activated).
    ``extra_path`` is put in front of ``sys.path`` for the run (what ``PYTHONPATH`` does for a
    subprocess: e.g. the repository root, so that ``-m src.train`` is found from another directory).
    ``timeout`` applies to subprocesses only.
    """
    argv = [str(a) for a in argv]
    if len(argv) < 2 or Path(argv[0]).name not in (Path(sys.executable).name, "python", "python3"):
        raise ValueError(f"expected [python, -m, module, ...] or [python, script, ...], got {argv[:3]}")
    if needs_own_process(argv):
        if argv[0] in ("python", "python3"):
            argv[0] = sys.executable
        return run_group(argv, cwd=cwd, env=None if env is None else dict(env), timeout=timeout)
    if argv[1] == "-m":
        if len(argv) < 3:
            raise ValueError("python -m needs a module name")
        target, rest, is_module = argv[2], argv[3:], True
    else:
        target, rest, is_module = argv[1], argv[2:], False
    out, err = io.StringIO(), io.StringIO()
    code = _run_here(target, rest, is_module, cwd, env, extra_path, out, err)
    return subprocess.CompletedProcess(argv, code, out.getvalue(), err.getvalue())


@contextlib.contextmanager
def process_group(argv: Sequence[str], **popen_kwargs) -> Iterator[subprocess.Popen]:
    """``subprocess.Popen(argv, **popen_kwargs)`` as the leader of a new process group (a session of its
    own); when the block ends, however it ends (a failed assertion, a timeout, Ctrl-C), every process still
    in that group (the DDP ranks and loader workers the command started) is killed and the leader reaped:
    a test leaves no orphans behind."""
    proc = subprocess.Popen(list(argv), start_new_session=True, **popen_kwargs)
    try:
        yield proc
    finally:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def group_alive(pgid: int) -> list[int]:
    """The processes of group ``pgid`` that have not exited (zombies left out), read from ``/proc``."""
    alive = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()  # after "pid (comm) "
        if fields[0] != "Z" and int(fields[2]) == pgid:
            alive.append(int(entry.name))
    return alive


def run_group(argv: Sequence[str], cwd=None, env: Mapping[str, str] | None = None,
              timeout: float | None = None) -> subprocess.CompletedProcess:  # fmt: skip
    """What ``subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)``
    returns, run in a process group that is killed whole when it times out (``subprocess.TimeoutExpired``
    is raised, as ``subprocess.run`` does) or when the command's own first process exits and leaves others."""
    with process_group(argv, cwd=cwd, env=None if env is None else dict(env), stdout=subprocess.PIPE,
                       stderr=subprocess.PIPE, text=True) as proc:  # fmt: skip
        out, err = proc.communicate(timeout=timeout)
    return subprocess.CompletedProcess(list(argv), proc.returncode, out, err)


def _run_here(target, rest, is_module, cwd, env, extra_path, out, err) -> int:
    from hydra.core.global_hydra import GlobalHydra

    saved_argv, saved_path, saved_env, saved_cwd = sys.argv[:], sys.path[:], dict(os.environ), os.getcwd()
    saved_loggers = {lg: _logger_state(lg) for lg in _loggers()}
    redirected = _redirect_console_handlers(out, err)
    code = 0
    try:
        if env is not None:
            os.environ.clear()
            os.environ.update(env)
        if cwd is not None:
            os.chdir(cwd)
        sys.path[:0] = [str(Path(p).resolve()) for p in extra_path]
        if not is_module:
            sys.path.insert(0, str(Path(target).resolve().parent))
        sys.argv = [target, *rest]
        GlobalHydra.instance().clear()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), warnings.catch_warnings():
            warnings.resetwarnings()  # as a fresh interpreter: every warning shown once more, on stderr
            warnings.simplefilter("default")
            warnings.filterwarnings("ignore", category=DeprecationWarning)
            warnings.showwarning = _print_warning
            try:
                if is_module:
                    runpy.run_module(target, run_name="__main__", alter_sys=True)
                else:
                    runpy.run_path(target, run_name="__main__")
            except SystemExit as stop:
                code = _exit_status(stop.code, err)
            except Exception:  # an uncaught exception: what the interpreter would print
                import traceback

                traceback.print_exc(file=err)
                code = 1
            finally:
                for stream in (sys.stdout, sys.stderr):
                    with contextlib.suppress(Exception):
                        stream.flush()
    finally:
        GlobalHydra.instance().clear()
        for handler, stream in redirected:
            handler.setStream(stream)
        for lg in _loggers():  # a logger the run created goes back to a new logger's state
            _restore_logger(lg, *saved_loggers.get(lg, ([], logging.NOTSET, True, False)))
        os.chdir(saved_cwd)
        os.environ.clear()
        os.environ.update(saved_env)
        sys.path[:] = saved_path
        sys.argv = saved_argv
    return code


def _loggers() -> list[logging.Logger]:
    """The root logger and every named one (placeholders left out)."""
    named = [lg for lg in logging.Logger.manager.loggerDict.values() if isinstance(lg, logging.Logger)]
    return [logging.getLogger(), *named]


def _redirect_console_handlers(out: io.StringIO, err: io.StringIO) -> list[tuple[logging.StreamHandler, object]]:
    """Console handlers that loggers already hold (Lightning adds one to its logger at import when the root
    logger has none) write to the run's ``out`` (those on standard output) or ``err`` (any other console
    stream) until the run ends, as they would in a process of its own. Their earlier streams are returned.
    File handlers and other ``StreamHandler`` subclasses (pytest's log capture) are left alone."""
    stdout = {id(sys.stdout), id(sys.__stdout__)}
    redirected = []
    for lg in _loggers():
        for handler in lg.handlers:
            if type(handler) is logging.StreamHandler and handler.stream not in (out, err):
                redirected.append((handler, handler.setStream(out if id(handler.stream) in stdout else err)))
    return redirected


def _logger_state(lg: logging.Logger) -> tuple:
    return lg.handlers[:], lg.level, lg.propagate, lg.disabled


def _restore_logger(lg: logging.Logger, handlers: list, level: int, propagate: bool, disabled: bool) -> None:
    """``lg`` as it was: the handlers a run added removed and closed (Hydra's console and file logs),
    those it removed put back, its level, propagation and disabled flag restored."""
    for handler in lg.handlers[:]:
        if handler not in handlers:
            lg.removeHandler(handler)
            with contextlib.suppress(Exception):
                handler.close()
    for handler in handlers:
        if handler not in lg.handlers:
            lg.addHandler(handler)
    lg.setLevel(level)
    lg.propagate, lg.disabled = propagate, disabled


def _print_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings go to the run's stderr, as a process of its own would print them."""
    sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


def _exit_status(code, err: io.StringIO) -> int:
    """The exit status ``sys.exit(code)`` gives a process (a message goes to stderr, status 1)."""
    if code is None:
        return 0
    if isinstance(code, int):
        return code
    print(code, file=err)
    return 1
