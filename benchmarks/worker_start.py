"""Benchmark: loader workers that never start (a deadlock at fork) and the time to a first batch, for every
worker start method (fork, forkserver with and without its preload, spawn), measured in one run.

What it models. A training process (a rank) starts the persistent workers of a loader while threads of its
own start and end at any moment. Two kinds of such threads are modelled, both running for the whole
measurement, in the process that starts the workers:

* ``python``: Python threads that start and end (what tqdm's monitor, a logger such as wandb, the run's own
  helper threads do: two threads that each start and join a short-lived ``threading.Thread`` in a loop),
  and ``multiprocessing`` queues that are put to, read and closed (the feeder thread of every queue, as
  earlier loaders leave behind: one thread doing that in a loop);
* ``native``: C++ threads that call into Python (two threads issuing asynchronous ``torch.distributed``
  all-reduces on a one-process gloo group with a Python callback on each future, which gloo's own thread
  runs when the reduction completes: what a DDP rank's communication hooks and future callbacks do, and
  any pybind11 or ctypes callback from a thread Python did not start). Each such call creates the
  thread's Python thread state and deletes it afterwards.

``all`` is both. ``aggressive`` (clearly more than a rank does, to see the rate at all within minutes):
four one-process gloo groups (two C++ threads each), each kept busy by a Python thread with eight
asynchronous all-reduces of 16,384 floats in flight, a Python callback on each.

On CPython 3.11 a forked child first deletes the thread states of the threads it did not
inherit (``PyOS_AfterFork_Child`` -> ``_PyThreadState_DeleteExcept``) under the interpreter's thread-list
lock. A Python thread creates and deletes its thread state holding the GIL, which the forking thread holds,
so it never holds that lock at the moment of a fork: ``python`` churn alone is expected to give no hang. A
C++ thread entering Python creates its thread state *before* it takes the GIL: when the fork lands in that
window the child inherits the lock held by a thread that does not exist in it and waits for ever: the
stack of the hung DDP runs, which the benchmark prints for the workers of every hung start (gdb). The
window is short, so the rate depends on how many such calls a second the rank makes and when the fork
lands; a ``forkserver`` or ``spawn`` worker is never forked from the rank, whatever its threads do.

Each row runs in a fresh process (``python -m worker_start``, as ``python -m src.train`` runs: its main
module imports torch, Lightning and the package, which a ``spawn`` or ``forkserver`` worker imports again
when it runs the main module as ``__mp_main__``), in a process group of its own that is killed whole at
its end, so that nothing is left behind. That process starts the churn, then repeats: a new
``DataLoader`` (``num_workers=2``, ``persistent_workers=True``, ``worker_init_fn=init_worker``, the
start method of the row) over a SYMSOL fixture read from PNG files (:class:`image2sphere.data.SymsolDataset`),
``iter``, the first batch of every worker, shut the workers down. A start in which a worker has not
delivered its first batch within ``--timeout`` seconds counts as a hang (its workers are then killed).

Printed per row: starts, hangs, the time from ``iter`` to the first batch (median and max; the first start
separately, as for ``forkserver`` it includes starting the fork server once per process) and to a batch
from every worker, and the median first batch's cost relative to ``fork`` under the same churn.
``forkserver`` is the start method of :func:`image2sphere.data.workers.worker_context` (what
``dataset.multiprocessing_context: null`` gives on Linux), which preloads torch, numpy, PIL, the datasets'
modules and the main module in the fork server; ``forkserver, no preload`` is the bare context.

Usage::

    python benchmarks/worker_start.py                    # 7 rows: about 18 minutes on a loaded 2-core CPU machine
    python benchmarks/worker_start.py --fork-starts 3000 --starts 1000 --rows fork-all,forkserver
    python benchmarks/worker_start.py --quick            # smoke run (10 starts per row, 2 for the slow ones)
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter, deque
from pathlib import Path

import torch
import torch.distributed as dist
import torch.utils.data._utils.signal_handling
from torch.utils.data import DataLoader

import image2sphere.training  # noqa: F401  (what python -m src.train imports: Lightning, the models, the entry)
from image2sphere.data.loading import collate_skipping_corrupt
from image2sphere.data.symsol import SymsolDataset
from image2sphere.data.workers import init_worker, worker_context

HERE = Path(__file__).resolve().parent
# row -> (start method, preload in the fork server, churn, which number of starts: --fork-starts, --starts or
# --slow-starts)
ROWS = {
    "fork-python": ("fork", False, "python", "fast"),
    "fork-all": ("fork", False, "all", "fork"),
    "forkserver": ("forkserver", True, "all", "fast"),
    "forkserver-bare": ("forkserver", False, "all", "slow"),
    "spawn": ("spawn", False, "all", "slow"),
    "fork-aggressive": ("fork", False, "aggressive", "fork"),
    "forkserver-aggressive": ("forkserver", True, "aggressive", "fast"),
}
LABELS = {
    "fork-python": "fork (today)",
    "fork-all": "fork (today)",
    "forkserver": "forkserver (new default)",
    "forkserver-bare": "forkserver, no preload",
    "spawn": "spawn",
    "fork-aggressive": "fork (today)",
    "forkserver-aggressive": "forkserver (new default)",
}
SHAPES = ("cube", "tetX")
WORKERS = 2


# ------------------------------------------------------------------------------------------- the churn
class Churn:
    """Threads of the rank that start and end while loaders start (see the module docstring)."""

    def __init__(self, mode: str):
        self.stop = threading.Event()
        self.counts: Counter[str] = Counter()
        self.threads: list[threading.Thread] = []
        self.python_idents: set[int] = set()
        loops = []
        if mode in ("python", "all"):
            loops += [self._threads, self._threads, self._queues]
        if mode in ("native", "all", "aggressive"):
            dist.init_process_group("gloo", store=dist.HashStore(), rank=0, world_size=1)
        if mode in ("native", "all"):
            loops += [self._callbacks, self._callbacks]
        if mode == "aggressive":
            groups = [dist.new_group([0], backend="gloo") for _ in range(4)]
            loops += [lambda g=g: self._in_flight(g) for g in groups]
        for loop in loops:
            thread = threading.Thread(target=loop, daemon=True)
            thread.start()
            self.threads.append(thread)
            self.python_idents.add(thread.ident)
        self.started = time.perf_counter()

    def _threads(self) -> None:
        while not self.stop.is_set():
            t = threading.Thread(target=time.sleep, args=(0.0005,))
            t.start()
            t.join()
            self.counts["Python threads"] += 1

    def _queues(self) -> None:
        while not self.stop.is_set():
            q = multiprocessing.Queue()
            q.put(b"x" * 64)
            q.get()
            q.close()
            q.join_thread()
            self.counts["queues"] += 1

    def _callback(self, future):
        # run by gloo's C++ thread when the future completed after .then() (else inline, in the caller)
        self.counts["native callbacks" if threading.get_ident() not in self.python_idents else "inline callbacks"] += 1
        return None

    def _callbacks(self) -> None:
        t = torch.zeros(1)
        while not self.stop.is_set():
            dist.all_reduce(t, async_op=True).get_future().then(self._callback).wait()

    def _in_flight(self, group, depth: int = 8) -> None:
        t = torch.zeros(16384)
        pending = deque()
        while not self.stop.is_set():
            while len(pending) < depth:
                pending.append(dist.all_reduce(t, group=group, async_op=True).get_future().then(self._callback))
            pending.popleft().wait()

    def rates(self) -> dict[str, float]:
        seconds = time.perf_counter() - self.started
        return {k: v / seconds for k, v in sorted(self.counts.items())}

    def close(self) -> None:
        self.stop.set()
        for thread in self.threads:
            thread.join(timeout=5)


# -------------------------------------------------------------------------------------- one start
def one_start(dataset, context, timeout: float) -> dict:
    """A new loader's workers started, a first batch from every worker, the workers shut down."""
    loader = DataLoader(dataset, batch_size=4, num_workers=WORKERS, persistent_workers=True,
                        worker_init_fn=init_worker, multiprocessing_context=context,
                        collate_fn=collate_skipping_corrupt, timeout=timeout)  # fmt: skip
    t0 = time.perf_counter()
    it = iter(loader)
    times = []
    try:
        for _ in range(WORKERS):  # batch k comes from worker k
            next(it)
            times.append(time.perf_counter() - t0)
    except RuntimeError as e:
        if "timed out" not in str(e):
            raise
    hang = len(times) < WORKERS
    result = {"hang": hang, "first": times[0] if times else None, "all": times[-1] if not hang else None}
    if hang:
        result["stuck in"] = [stuck_in(w.pid) for w in it._workers]
        print(json.dumps(result), flush=True)  # before the clean-up
        # torch's SIGCHLD handler would raise in this process for a worker it knows killed by a signal
        torch.utils.data._utils.signal_handling._remove_worker_pids(id(it))
        it._worker_pids_set = False
        for w in it._workers:
            try:
                os.kill(w.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    it._shutdown_workers()
    return result


def stuck_in(pid: int) -> str:
    """Where process ``pid`` waits: the innermost CPython functions of its stack that name the fork or the
    thread states (gdb, when installed), else its kernel wait channel."""
    try:
        out = subprocess.run(["gdb", "-p", str(pid), "-batch", "-ex", "bt"], capture_output=True, text=True,
                             timeout=60).stdout  # fmt: skip
        names = [
            line.split(" in ")[1].split(" (")[0] for line in out.splitlines() if line.startswith("#") and " in " in line
        ]
        wanted = [n for n in names if "AfterFork" in n or "DeleteExcept" in n or n == "os_fork_impl"]
        if wanted:
            return " <- ".join(wanted)
    except (OSError, subprocess.SubprocessError, IndexError):
        pass
    try:
        return "wchan " + Path(f"/proc/{pid}/wchan").read_text()
    except OSError:
        return "?"


def fork_server_state() -> dict:
    """Threads of the fork server and whether it ignores SIGTERM (``/proc``)."""
    from multiprocessing import forkserver

    pid = getattr(forkserver._forkserver, "_forkserver_pid", None)
    if pid is None:
        return {}
    status = Path(f"/proc/{pid}/status").read_text()
    ignored = int(status.split("SigIgn:")[1].split()[0], 16)
    return {"server threads": len(os.listdir(f"/proc/{pid}/task")),
            "server ignores SIGTERM": bool(ignored >> (signal.SIGTERM - 1) & 1)}  # fmt: skip


def child(args) -> None:
    """One row, in this process: prints one JSON line per start, then one with the churn rates."""
    method, preload, churn_mode, _ = ROWS[args.child]
    torch.set_num_threads(1)
    dataset = SymsolDataset(args.root, "train", SHAPES, image_size=16, seed=0)
    context = worker_context(method) if preload else multiprocessing.get_context(method)
    churn = Churn(churn_mode)
    time.sleep(0.5)
    extra = {}
    try:
        for k in range(args.starts):
            result = one_start(dataset, context, args.timeout)
            if not result["hang"]:  # a hang was printed before its clean-up
                print(json.dumps(result), flush=True)
            if k == 0 and method == "forkserver":
                extra = fork_server_state()
    finally:
        rates = churn.rates()
        churn.close()
    print(json.dumps({"rates": rates, **extra}), flush=True)


# ------------------------------------------------------------------------------------------ the runner
def run_row(row: str, starts: int, root: Path, timeout: float) -> dict:
    """Run ``row`` in a fresh process group (killed whole at the end, whatever happened); its results."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep),
               OMP_NUM_THREADS="1")  # fmt: skip
    argv = [sys.executable, "-m", "worker_start", "--child", row, "--starts", str(starts), "--root", str(root),
            "--timeout", str(timeout)]  # fmt: skip
    limit = 120 + starts * 30 + 60  # a hang costs --timeout; a spawn start several seconds
    results, extra, error = [], {}, ""
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, env=env, cwd=HERE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)  # fmt: skip
    try:
        out, err = proc.communicate(timeout=limit)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        error = f"stopped after {limit} s"
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # the fork server, the resource tracker, any worker left
        except ProcessLookupError:
            pass
        proc.wait()
    for line in out.splitlines():
        if line.startswith("{"):
            record = json.loads(line)
            (extra.update(record) if "rates" in record else results.append(record))
    if proc.returncode not in (0, -signal.SIGKILL) or not results:
        error = error or f"exit status {proc.returncode}: {err.strip()[-2000:]}"
    return {"row": row, "results": results, "extra": extra, "error": error, "seconds": time.perf_counter() - t0}


def summarise(r: dict) -> dict:
    ok = [x for x in r["results"] if not x["hang"]]
    first = [x["first"] for x in ok]
    return {
        "starts": len(r["results"]),
        "hangs": sum(x["hang"] for x in r["results"]),
        "start 1": r["results"][0]["first"] if r["results"] and not r["results"][0]["hang"] else None,
        "median": statistics.median(first[1:] or first) if first else None,
        "max": max(first) if first else None,
        "every worker": statistics.median([x["all"] for x in ok[1:] or ok]) if ok else None,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rows", default=",".join(ROWS), help=f"comma-separated, of {', '.join(ROWS)}")
    parser.add_argument("--fork-starts", type=int, default=1000, help="starts of the fork row with all the churn")
    parser.add_argument("--starts", type=int, default=300, help="starts of the forkserver and fork-python rows")
    parser.add_argument("--slow-starts", type=int, default=20, help="starts of the spawn and bare forkserver rows")
    parser.add_argument("--timeout", type=float, default=20.0, help="seconds a start may take before it is a hang")
    parser.add_argument("--quick", action="store_true", help="10 starts per row, 2 for the slow ones")
    parser.add_argument("--child", choices=list(ROWS), help=argparse.SUPPRESS)
    parser.add_argument("--root", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        return child(args)

    from _machine import cpu_model, load_line  # benchmarks/_machine.py, beside this script
    from image2sphere.data.fixtures.symsol import write_symsol

    rows = [r.strip() for r in args.rows.split(",") if r.strip()]
    unknown = set(rows) - set(ROWS)
    if unknown:
        parser.error(f"unknown rows {sorted(unknown)} (known: {', '.join(ROWS)})")
    starts = {"fork": 10, "fast": 10, "slow": 2} if args.quick else \
        {"fork": args.fork_starts, "fast": args.starts, "slow": args.slow_starts}  # fmt: skip
    t_start = time.perf_counter()
    print(f"CPU: {cpu_model()}; Python {sys.version.split()[0]}, torch {torch.__version__}; {load_line('at start')}")
    print(f"each start: DataLoader(num_workers={WORKERS}, persistent_workers=True, worker_init_fn=init_worker), "
          f"a first batch from every worker within {args.timeout:g} s or a hang\n", flush=True)  # fmt: skip
    summaries = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "symsol"
        write_symsol(root, shapes=SHAPES, per_split={"train": 8, "test": 2}, image_size=24)
        for row in rows:
            method, preload, churn, speed = ROWS[row]
            r = run_row(row, starts[speed], root, args.timeout)
            s = summaries[row] = summarise(r)
            rates = ", ".join(f"{v:.0f} {k}/s" for k, v in r["extra"].get("rates", {}).items())
            server = {k: v for k, v in r["extra"].items() if k != "rates"}
            print(f"  {row}: {LABELS[row]}, churn {churn}: {s['starts']} starts, {s['hangs']} hangs "
                  f"({r['seconds']:.0f} s); churn {rates or 'n/a'}" + (f"; fork server: {server}" if server else ""),
                  flush=True)  # fmt: skip
            for where in sorted({w for x in r["results"] for w in x.get("stuck in", [])}):
                print(f"    a hung start's worker waits in: {where}", flush=True)
            if r["error"]:
                print(f"    ERROR: {r['error']}", flush=True)

    base = {
        churn: summaries[row]["median"] for row, (m, _, churn, _) in ROWS.items() if m == "fork" and row in summaries
    }
    cols = [("row", 21, "<"), ("start method", 24, "<"), ("churn", 10, "<"), ("starts", 6, ">"), ("hangs", 5, ">"),
            ("1st [s]", 7, ">"), ("median [s]", 10, ">"), ("max [s]", 7, ">"), ("all [s]", 7, ">"),
            ("vs fork", 7, ">")]  # fmt: skip
    print("\n" + "  ".join(f"{title:{align}{w}}" for title, w, align in cols))

    def fmt(x, spec=".3f"):
        return "-" if x is None else f"{x:{spec}}"

    for row, s in summaries.items():
        churn = ROWS[row][2]
        ratio = s["median"] / base[churn] if base.get(churn) and s["median"] is not None else None
        cells = [row, LABELS[row], churn, str(s["starts"]), str(s["hangs"]), fmt(s["start 1"], ".2f"),
                 fmt(s["median"]), fmt(s["max"], ".2f"), fmt(s["every worker"]), fmt(ratio, ".1f")]  # fmt: skip
        print("  ".join(f"{c:{align}{w}}" for c, (_, w, align) in zip(cells, cols, strict=True)))
    print(
        "\n1st: the first start of the process (forkserver: starts the fork server, which imports its preload); "
        "median, max: time from iter() to the first batch (median over the starts after the first); all: to a "
        "batch from every worker; vs fork: median / fork's median under the same churn. A hang: a worker that "
        f"gave no batch within {args.timeout:g} s (on CPython 3.11, stuck in PyOS_AfterFork_Child)."
    )
    print(f"total benchmark time: {time.perf_counter() - t_start:.0f} s; {load_line('at end')}")


if __name__ == "__main__":
    main()
