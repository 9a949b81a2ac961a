"""What the loader workers' fork server sets up in itself: imported by the server only, as the first name of
:data:`image2sphere.data.workers.FORKSERVER_PRELOAD`; anywhere else importing it changes nothing.

* **SIGTERM**: the server ignores it, as multiprocessing's resource tracker does, and the processes it
  forks get SIGTERM's default back. A SIGTERM sent to the whole process group (``kill -- -pgid``, SLURM's
  pre-emption) must not end the server under a rank that decides when to stop: its workers would see their
  parent change and quit (torch's check), and the rank fail on its next batch. The server still ends when
  its rank and the rank's workers have all ended (its "alive" pipe is then closed), and on SIGKILL.
* **runpy's warning**: a ``forkserver`` worker runs the program's main module again as ``__mp_main__``
  when it starts (``multiprocessing.spawn.prepare``). For a program started as ``python -m src.train`` the
  server has already imported ``src.train`` by that name
  (:func:`~image2sphere.data.workers.worker_context` preloads it, so that a worker finds its imports done),
  and ``runpy`` would warn in every worker that ``'src.train' found in sys.modules after import of package
  'src', but prior to execution of 'src.train'``: one line per worker start on the user's terminal, about
  nothing (the module is run once more on purpose). The filter, inherited by every worker the server
  forks, silences exactly that message.
"""

from __future__ import annotations

import os
import signal
import sys
import warnings


def _in_fork_server() -> bool:
    """Whether this import runs inside ``multiprocessing.forkserver.main`` (the server's preload)."""
    forkserver = sys.modules.get("multiprocessing.forkserver")
    frame = sys._getframe(1) if forkserver is not None else None
    while frame is not None and frame.f_code is not forkserver.main.__code__:
        frame = frame.f_back
    return frame is not None


if _in_fork_server():
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    os.register_at_fork(after_in_child=lambda: signal.signal(signal.SIGTERM, signal.SIG_DFL))
    warnings.filterwarnings(
        "ignore",
        message=r"'[\w.]+' found in sys\.modules after import of package '[\w.]+', but prior to execution of",
        category=RuntimeWarning,
    )
