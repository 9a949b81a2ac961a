"""How many DataLoader workers a loader starts, how they start, and what each runs when it starts.

``dataset.num_workers`` is an integer >= 0 or ``auto`` (:func:`check_num_workers`). ``auto`` resolves
to :func:`auto_num_workers`: the CPUs this process may run on (:func:`available_cpus`, which also sizes
the SYMSOL renderer's threads) shared out between the training processes of this machine
(:func:`local_processes`). Every worker runs :func:`init_worker` when it starts.

``dataset.multiprocessing_context`` is how the workers start (:func:`check_multiprocessing_context`):
``fork``, ``forkserver`` or ``spawn``; ``null`` is :data:`DEFAULT_START_METHOD`, ``forkserver`` where the
platform has it (Linux, macOS), else ``spawn``. Not ``fork``: a rank has threads that start and end at any
moment (the callbacks of ``torch.distributed`` futures and other C++ threads calling into Python, queue
feeder threads of earlier loaders, progress bars, loggers), and on CPython 3.11 a worker forked while one
of them holds the interpreter's thread-list lock waits for that lock for ever, in
``PyOS_AfterFork_Child`` -> ``_PyThreadState_DeleteExcept`` (measured: ``benchmarks/worker_start.py``). A
``forkserver`` worker is forked from a single-threaded server process started once per rank
(:func:`worker_context`, which preloads torch, numpy, PIL and the datasets' modules there so that a
worker starts in a fraction of a second); a ``spawn`` worker is a fresh interpreter. Both receive the
dataset and ``worker_init_fn`` pickled (every dataset of :mod:`image2sphere.data` pickles cheaply: no open
file handle, big indices as tensors, which reach the workers as shared memory).
"""

from __future__ import annotations

import multiprocessing
import os
import select
import signal
import sys
import threading
import time

from torch.utils.data import get_worker_info

from image2sphere.checks import ConfigError, check_int

__all__ = [
    "AUTO",
    "AUTO_WORKERS_CAP",
    "DEFAULT_START_METHOD",
    "FORKSERVER_PRELOAD",
    "START_METHODS",
    "auto_num_workers",
    "available_cpus",
    "check_multiprocessing_context",
    "check_num_workers",
    "init_worker",
    "local_processes",
    "obey_sigterm_from_parent_only",
    "rank_pid",
    "worker_context",
]

AUTO_WORKERS_CAP = 8
AUTO = "auto"
START_METHODS = ("fork", "forkserver", "spawn")
DEFAULT_START_METHOD = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
# imported once by the fork server, so that its workers find them imported: what unpickling a dataset,
# the collate function and init_worker needs (image2sphere.data imports every Dataset module, not Lightning),
# after image2sphere.data.fork_server, which sets the server up (SIGTERM, runpy's warning)
FORKSERVER_PRELOAD = (
    "image2sphere.data.fork_server",
    "torch",
    "numpy",
    "PIL.Image",
    "image2sphere.data",
    "image2sphere.data.workers",
)


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask; ``os.cpu_count()`` where there is none)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def local_processes(trainer: object | None = None) -> int:
    """Training processes on this machine, each of which starts its own loader workers.

    ``LOCAL_WORLD_SIZE`` when set (torchrun and torch.distributed launchers set it), else the number
    of devices of a Lightning ``trainer`` (one process per device under DDP), else 1.
    """
    value = os.environ.get("LOCAL_WORLD_SIZE", "")
    if value.strip().isdigit() and int(value) > 0:
        return int(value)
    devices = getattr(trainer, "num_devices", None) if trainer is not None else None
    if isinstance(devices, int) and not isinstance(devices, bool) and devices > 0:
        return devices
    return 1


def auto_num_workers(cpus: int | None = None, processes: int | None = None) -> int:
    """What ``num_workers: auto`` resolves to: ``min(8, cpus // processes - 1)``, at least 0.

    ``cpus``: :func:`available_cpus`; ``processes``: training processes on this machine
    (:func:`local_processes`). One CPU per process is left to the training loop itself; beyond 8
    workers a loader rarely gets faster and every worker holds a copy of the dataset's index.
    """
    cpus = available_cpus() if cpus is None else int(cpus)
    processes = 1 if processes is None else max(1, int(processes))
    return max(0, min(AUTO_WORKERS_CAP, cpus // processes - 1))


def check_num_workers(value: object, key: str = "dataset.num_workers") -> int | str:
    """A valid ``num_workers`` setting: an integer >= 0, or ``"auto"`` (``None`` means ``"auto"``);
    ``ValueError`` naming ``key`` for anything else."""
    if value is None or (isinstance(value, str) and value.strip().lower() == AUTO):
        return AUTO
    note = f" or auto (null means auto: min({AUTO_WORKERS_CAP}, CPUs // local training processes - 1))"
    return check_int(key, value, 0, note=note)


def check_multiprocessing_context(value: object, key: str = "dataset.multiprocessing_context") -> str | None:
    """A valid worker start method: ``"fork"``, ``"forkserver"`` or ``"spawn"`` (any case), or ``None`` (the
    default, :data:`DEFAULT_START_METHOD`); ``ValueError`` naming ``key`` for anything else, or for a method
    this platform lacks."""
    if value is None:
        return None
    method = value.strip().lower() if isinstance(value, str) else None
    if method not in START_METHODS:
        raise ConfigError(
            f"{key} must be one of {', '.join(START_METHODS)} or null (null: {DEFAULT_START_METHOD}, the safe "
            f"default; fork can deadlock a worker at start), got {value!r}"
        )
    if method not in multiprocessing.get_all_start_methods():
        available = ", ".join(multiprocessing.get_all_start_methods())
        raise ConfigError(f"{key}={method} is not available on this platform (it has {available})")
    return method


def worker_context(method: str | None = None) -> multiprocessing.context.BaseContext:
    """The multiprocessing context that starts a loader's workers: ``method`` (``None``:
    :data:`DEFAULT_START_METHOD`). For ``forkserver`` the fork server of this process, started at the first
    worker start, preloads :data:`FORKSERVER_PRELOAD` and the main module when the program runs as ``python
    -m module`` (a ``spawn`` or ``forkserver`` worker runs the main module again, as ``__mp_main__``: with
    its imports already done in the server, that costs next to nothing); the modules another caller set
    are kept. A preload set after the server started has no effect (the server lives as long as the
    process)."""
    method = check_multiprocessing_context(method, "multiprocessing_context") or DEFAULT_START_METHOD
    context = multiprocessing.get_context(method)
    if method == "forkserver":
        from multiprocessing import forkserver

        current = list(getattr(forkserver._forkserver, "_preload_modules", None) or [])
        wanted = [*FORKSERVER_PRELOAD, *_main_module()]
        if any(name not in current for name in wanted):
            context.set_forkserver_preload(current + [name for name in wanted if name not in current])
    return context


def _main_module() -> list[str]:
    """``[name]`` of the main module when it was run as ``python -m name`` (not a package's ``__main__``,
    which multiprocessing does not run again in its children), else ``[]``."""
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    name = getattr(spec, "name", None)
    return [name] if name and name != "__main__" and not name.endswith(".__main__") else []


def init_worker(worker_id: int) -> None:
    """The DataLoader ``worker_init_fn`` of :class:`~image2sphere.data.datamodule.PoseDataModule`: calls
    ``init_worker()`` on the worker's copy of the dataset when it has one (the ModelNet10-SO(3) reader
    closes the LMDB environments inherited through ``fork`` there; each worker opens its own on first read).

    Signals (:func:`obey_sigterm_from_parent_only`): a Ctrl-C or a SIGTERM sent to the whole process group
    (a terminal, SLURM's pre-emption) must not kill a worker under its rank, which decides when to stop
    (:mod:`image2sphere.training.stop`) and then shuts its workers down. That holds for every start method:
    the rank is the process that started the worker (:func:`rank_pid`), its parent under ``fork`` and
    ``spawn``, not under ``forkserver`` (the fork server is)."""
    obey_sigterm_from_parent_only()
    info = get_worker_info()
    init = getattr(info.dataset, "init_worker", None) if info is not None else None
    if callable(init):
        init()


def rank_pid() -> int:
    """In a loader worker: the pid of the process that started it (its rank), whatever the start method.

    ``multiprocessing.parent_process()``: the creator's pid travels with the process object. Under
    ``forkserver`` ``os.getppid()`` is the fork server's pid instead. Elsewhere: ``os.getppid()``."""
    parent = multiprocessing.parent_process()
    pid = getattr(parent, "pid", None)
    return int(pid) if pid else os.getppid()


def obey_sigterm_from_parent_only(rank: int | None = None) -> None:
    """In a loader worker: ignore Ctrl-C; obey a SIGTERM only when the worker's rank (``rank``, default
    :func:`rank_pid`: the process that started it) sent it, and ignore one from anyone else.

    A rank ends its persistent workers at exit with ``Process.terminate()``, a SIGTERM (torch leaves them
    to Python's ``multiprocessing`` then), so a worker that ignored every SIGTERM would keep its rank
    waiting forever at exit (seen: a DDP rank hung in ``multiprocessing``'s exit function). A SIGTERM from
    outside (``kill``, ``scancel``, SLURM signalling every process of the job) is left to the rank. The
    signal is blocked in the worker and taken by a thread that reads who sent it (``sigwaitinfo``).

    Once the rank is gone, any SIGTERM ends the worker. A worker whose parent is not its rank (a
    ``forkserver`` worker, whose parent is the fork server) also ends by itself when its rank ends: torch's
    own check (the worker's parent changed) would never fire there, and a rank killed with SIGKILL would
    leave its workers, and the fork server they keep open, behind."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    rank = rank_pid() if rank is None else int(rank)
    parent = os.getppid()
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})  # threads started from here on inherit it

    def take_sigterm() -> None:
        while True:
            info = signal.sigwaitinfo({signal.SIGTERM})
            if info.si_pid == rank or os.getppid() != parent or not _alive(rank):  # the rank (or it is gone)
                os._exit(128 + signal.SIGTERM)

    threading.Thread(target=take_sigterm, name="sigterm-from-rank", daemon=True).start()
    if parent != rank:
        threading.Thread(target=_exit_with, args=(rank,), name="exit-with-rank", daemon=True).start()


def _alive(pid: int) -> bool:
    """Whether process ``pid`` exists (a zombie counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _exit_with(pid: int) -> None:
    """End this process (status 0, as a torch worker whose parent is gone) when process ``pid`` ends: a
    pidfd that becomes readable, else a check every second."""
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        os._exit(0)
    except (AttributeError, OSError):  # not Linux >= 5.3
        fd = None
    if fd is not None:
        select.select([fd], [], [])
    else:
        while _alive(pid):
            time.sleep(1.0)
    os._exit(0)
