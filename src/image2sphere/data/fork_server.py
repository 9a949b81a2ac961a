"""Imported by the loader workers' fork server only (the first name of
:data:`image2sphere.data.workers.FORKSERVER_PRELOAD`), never by a training process.

A ``forkserver`` worker runs the program's main module again as ``__mp_main__`` when it starts
(``multiprocessing.spawn.prepare``). For a program started as ``python -m src.train`` the server has already
imported ``src.train`` by that name (:func:`~image2sphere.data.workers.worker_context` preloads it, so that
a worker finds its imports done), and ``runpy`` then warns in every worker that ``'src.train' found in
sys.modules after import of package 'src', but prior to execution of 'src.train'``: one line per worker
start on the user's terminal, about nothing (the module is run once more on purpose, with its imports
already in place). The filter below, installed in the server and inherited by every worker it forks,
silences exactly that message.
"""

from __future__ import annotations

import warnings

warnings.filterwarnings(
    "ignore",
    message=r"'[\w.]+' found in sys\.modules after import of package '[\w.]+', but prior to execution of",
    category=RuntimeWarning,
)
