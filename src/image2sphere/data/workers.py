"""How many DataLoader workers a loader starts, and what each runs when it starts.

``dataset.num_workers`` is an integer >= 0 or ``auto`` (:func:`check_num_workers`). ``auto`` resolves
to :func:`auto_num_workers`: the CPUs this process may run on (:func:`available_cpus`, which also sizes
the SYMSOL renderer's threads) shared out between the training processes of this machine
(:func:`local_processes`). Every worker runs :func:`init_worker` when it starts.
"""

from __future__ import annotations

import os
import signal
import threading

from torch.utils.data import get_worker_info

from image2sphere.checks import check_int

__all__ = [
    "AUTO",
    "AUTO_WORKERS_CAP",
    "auto_num_workers",
    "obey_sigterm_from_parent_only",
    "available_cpus",
    "check_num_workers",
    "init_worker",
    "local_processes",
]

AUTO_WORKERS_CAP = 8
AUTO = "auto"


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


def init_worker(worker_id: int) -> None:
    """The DataLoader ``worker_init_fn`` of :class:`~image2sphere.data.datamodule.PoseDataModule`: calls
    ``init_worker()`` on the worker's copy of the dataset when it has one (the ModelNet10-SO(3) reader
    closes the LMDB environments inherited through ``fork`` there; each worker opens its own on first read).

    Signals (:func:`obey_sigterm_from_parent_only`): a Ctrl-C or a SIGTERM sent to the whole process group
    (a terminal, SLURM's pre-emption) must not kill a worker under its rank, which decides when to stop
    (:mod:`image2sphere.training.stop`) and then shuts its workers down."""
    obey_sigterm_from_parent_only()
    info = get_worker_info()
    info = get_worker_info()
    init = getattr(info.dataset, "init_worker", None) if info is not None else None
    if callable(init):
        init()


def obey_sigterm_from_parent_only() -> None:
    """In a loader worker: ignore Ctrl-C; obey a SIGTERM only when the worker's own process (its rank) sent
    it, and ignore one from anyone else.

    A rank ends its persistent workers at exit with ``Process.terminate()``, a SIGTERM (torch leaves them
    to Python's ``multiprocessing`` then), so a worker that ignored every SIGTERM would keep its rank
    waiting forever at exit (seen: a DDP rank hung in ``multiprocessing``'s exit function). A SIGTERM from
    outside (``kill``, ``scancel``, SLURM signalling every process of the job) is left to the rank. The
    signal is blocked in the worker and taken by a thread that reads who sent it (``sigwaitinfo``)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    parent = os.getppid()
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})  # threads started from here on inherit it

    def take_sigterm() -> None:
        while True:
            info = signal.sigwaitinfo({signal.SIGTERM})
            if info.si_pid == parent or os.getppid() != parent:  # the rank (or the rank is gone)
                os._exit(128 + signal.SIGTERM)

    threading.Thread(target=take_sigterm, name="sigterm-from-rank", daemon=True).start()
