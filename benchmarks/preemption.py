"""Pre-emption stress check: a two-process DDP run stopped by SIGTERM at many moments must always end.

``python benchmarks/preemption.py [--moments 22] [--seed 0] [--out DIR]`` (from the repository root, on the
CPU; about 30 s a moment on two cores) trains a tiny two-process DDP run (Lightning's
``trainer=ddp`` on the CPU, gloo, the default callbacks, two loader workers a loader) once without
interruption, then once per *moment* of a seeded schedule with a SIGTERM at that moment, and checks for each:

* the whole process group (both ranks, their data-loading workers) has exited within ``--bound``
  seconds of the signal; rank 0 exited with 143 (128 + SIGTERM) and said how to go on;
* whenever ``last.ckpt`` exists it is complete (read with ``weights_only=True``), and no temporary file
  of an interrupted write is left;
* resuming from it (``ckpt_path=...``, two processes again) ends as the uninterrupted run: the same
  final weights and the same test metrics.

A moment is a *phase* of the run, its n-th occurrence, the rank that sends the signal, and the target:
``rank0`` (rank 0 alone, as ``kill <pid>`` does) or ``group`` (every process of the run at once, as SLURM
signals a job on pre-emption or ``scancel``). The phases are the places where a signal used to hurt:
setting up (before the first checkpoint), the sanity check, between forward and backward, inside the
optimizer's step, validation, inside the write of a checkpoint, the end of an epoch, the end of training,
the test. The signal is sent from inside that phase by ``SignalAt``, a callback the run is given on its
command line (:mod:`image2sphere.testing.signal_at`), so that it lands there every time; the schedule adds
moments timed from outside (seconds after the start or after the first ``last.ckpt``), which land wherever
the run happens to be.
Such a signal may land where the run has no say: before its handlers exist (the first seconds, while
Python imports; Python's default ends the process at once, and when that is a rank Lightning is just
starting, Lightning kills rank 0 within 5 s) or after its work is done. Those outcomes pass when
nothing was lost: no checkpoint had been written, or the run finished with the uninterrupted run's
metrics.

On a run that does not exit within the bound, its stacks are dumped with ``py-spy`` when that is
installed, and the process group is killed: nothing is left behind. The exit status is the number of
failed moments. ``tests/test_scaling.py`` runs the hardest moments in the slow tier.

The run is the tests' tiny one (:data:`image2sphere.testing.tiny.TINY`) on two processes, with the
settings of :data:`RUN` laid over it.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from image2sphere.config_text import override_key
from image2sphere.testing.commands import group_alive, process_group
from image2sphere.testing.signal_at import PHASES
from image2sphere.testing.tiny import TINY

# Laid over the tiny settings: what a user has, every default callback (the tqdm progress bar on, SO(3)
# plots, BatchNorm statistics, checkpoints) and two loader workers per loader (the real datasets' configs
# start workers), on 2 ranks x batch 2: 4 training batches a rank per epoch, 2 epochs, one validation batch
# a rank, a sanity check, 2 test batches a rank. No logger: the stop writes nothing a logger holds.
OVER_TINY = [
    "trainer=ddp",
    "trainer.devices=2",
    "trainer.accelerator=cpu",
    "trainer.max_epochs=2",
    "trainer.num_sanity_val_steps=1",
    "trainer.strategy.timeout.seconds=60",
    "dataset.batch_size=2",
    "dataset.num_workers=2",
    "logger=none",
]
RUN = [o for o in TINY if override_key(o) not in {override_key(p) for p in OVER_TINY}] + OVER_TINY
# phase -> (occurrences in the run above on each rank, ranks that pass it)
MOMENT_PHASES: dict[str, tuple[int, tuple[int, ...]]] = {
    "fit_start": (1, (0, 1)),
    "sanity_check": (1, (0, 1)),
    "forward_backward": (8, (0, 1)),
    "optimizer_step": (8, (0, 1)),
    "validation": (2, (0, 1)),
    "checkpoint_write": (2, (0,)),  # rank 0 writes
    "epoch_end": (2, (0, 1)),
    "train_end": (1, (0, 1)),
    "test": (2, (0, 1)),
}
TIMED = ("after_start", "after_first_checkpoint")


assert set(MOMENT_PHASES) == set(PHASES)  # every phase SignalAt knows


# ---------------------------------------------------------------------------------------------- the schedule
@dataclass
class Moment:
    """Where the signal lands: a phase of :data:`MOMENT_PHASES` (its ``occurrence`` on ``rank``), or a
    time of :data:`TIMED` (``delay`` seconds after the start or after the first ``last.ckpt``)."""

    name: str
    phase: str
    target: str  # "rank0" or "group"
    occurrence: int = 1
    rank: int = 0
    delay: float = 0.0

    @property
    def timed(self) -> bool:
        return self.phase in TIMED


def schedule(n: int, seed: int) -> list[Moment]:
    """``n`` moments: every phase to rank 0 alone and to the whole group (at a seeded occurrence, sent by
    a seeded rank), then moments timed from outside at seeded delays."""
    rng = random.Random(seed)
    moments = []
    for phase, (count, ranks) in MOMENT_PHASES.items():
        for target in ("rank0", "group"):
            occurrence = rng.randint(1, count)
            rank = 0 if target == "rank0" else rng.choice(ranks)
            moments.append(Moment(f"{phase}#{occurrence}/{target}", phase, target, occurrence, rank))
    i = 0
    while len(moments) < n:
        phase, target = TIMED[i % 2], ("rank0", "group")[(i // 2) % 2]
        # inside the run: from the imports to the first epoch, and in the second epoch (about 5 s long here)
        delay = round(rng.uniform(2.0, 10.0) if phase == "after_start" else rng.uniform(0.0, 1.5), 2)
        moments.append(Moment(f"{phase}+{delay}s/{target}", phase, target, delay=delay))
        i += 1
    return moments[:n] if n < len(moments) else moments


# ---------------------------------------------------------------------------------------------- the harness
def dump_stacks(pgid: int, dump: Path) -> None:
    """The Python stacks of every process of group ``pgid`` into ``dump``, with ``py-spy`` where it is
    installed (a hung run's record)."""
    if not shutil.which("py-spy"):
        return
    with open(dump, "w") as f:
        for pid in group_alive(pgid):
            f.write(f"==== py-spy dump --pid {pid}\n")
            f.flush()
            subprocess.run(["py-spy", "dump", "--pid", str(pid)], stdout=f, stderr=subprocess.STDOUT, timeout=60)


def run_and_signal(argv: list[str], log: Path, timeout: float, env: dict | None = None,
                   moment: Moment | None = None, watch: Path | None = None) -> dict:  # fmt: skip
    """Run ``argv`` as a process group of its own (:func:`~image2sphere.testing.commands.process_group`:
    whatever is left of it is killed when this returns), output to ``log``; for a timed ``moment``, send
    SIGTERM ``moment.delay`` s after the start or after ``watch`` appears. Returns the exit status of its
    first process (``returncode``), when the last process of the group exited (``ended``), when the
    signal was sent (``sent``) and ``hung``: still running at ``timeout`` (its stacks then beside ``log``)."""
    start = time.monotonic()
    sent = None
    with open(log, "w") as out, process_group(argv, stdout=out, stderr=subprocess.STDOUT, env=env) as proc:
        while time.monotonic() - start < timeout:
            if moment is not None and moment.timed and sent is None:
                since = start if moment.phase == "after_start" else _appeared(watch)
                if since is not None and time.monotonic() - since >= moment.delay:
                    sent = time.time()
                    _send(proc.pid, moment.target)
            if proc.poll() is not None and not group_alive(proc.pid):
                return {"returncode": proc.returncode, "ended": time.time(), "sent": sent, "hung": False}
            time.sleep(0.02)
        dump_stacks(proc.pid, log.with_suffix(".stacks.txt"))
    return {"returncode": proc.returncode, "ended": time.time(), "sent": sent, "hung": True}


_FIRST_SEEN: dict[Path, float] = {}


def _appeared(path: Path | None) -> float | None:
    if path is None:
        return None
    if path not in _FIRST_SEEN and path.exists():
        _FIRST_SEEN[path] = time.monotonic()
    return _FIRST_SEEN.get(path)


def _send(pid: int, target: str) -> None:
    """SIGTERM to the run's first process (``rank0``) or to its whole process group (``group``)."""
    try:
        if target == "group":
            os.killpg(pid, signal.SIGTERM)  # the first process leads the group
        else:
            os.kill(pid, signal.SIGTERM)
    except ProcessLookupError:
        pass


def train_argv(extra: list[str], data_dir: Path, run_dir: Path) -> list[str]:
    return [sys.executable, "-m", "src.train", *RUN, f"paths.data_dir={data_dir}",
            f"paths.log_dir={run_dir.parent / 'logs'}", f"hydra.run.dir={run_dir}", *extra]  # fmt: skip


def signal_overrides(moment: Moment, stamp: Path) -> list[str]:
    if moment.timed:
        return []
    key = "+callbacks.signal_at"
    return [f"{key}._target_=image2sphere.testing.signal_at.SignalAt", f"{key}.phase={moment.phase}",
            f"{key}.occurrence={moment.occurrence}", f"{key}.rank={moment.rank}",
            f"{key}.target={'group' if moment.target == 'group' else 'rank'}", f"{key}.stamp={stamp}"]  # fmt: skip


def final_weights(run_dir: Path, resumed_from: Path) -> dict:
    import torch

    last = run_dir / "checkpoints" / "last.ckpt"
    path = last if last.is_file() else resumed_from  # a resume of a finished training trains nothing
    return torch.load(path, map_location="cpu", weights_only=True)


def differing_metrics(a: dict, b: dict, rel: float = 1e-5) -> list[str]:
    """The metric keys whose values differ (timings left out)."""
    keys = {k for k, v in a.items() if isinstance(v, float) and not k.endswith("_seconds")}
    return sorted(k for k in keys if k not in b or not math.isclose(a[k], b[k], rel_tol=rel, abs_tol=1e-6))


def check_moment(moment: Moment, root: Path, data_dir: Path, reference: Path, bound: float,
                 env: dict | None = None, give_up: float | None = None) -> dict:  # fmt: skip
    """Run one moment (stop, checks, resume) under ``root``; a dict of what was measured and ``problems``.
    A run still alive ``give_up`` seconds after its start (default: ``bound`` + 240) counts as hung."""
    import torch

    from image2sphere.training.checkpoint import load_checkpoint

    stopped, resumed = root / "stopped", root / "resumed"
    stamp = root / "signal_sent"
    ckpt = stopped / "checkpoints" / "last.ckpt"
    give_up = bound + 240 if give_up is None else give_up
    result = run_and_signal(train_argv(signal_overrides(moment, stamp), data_dir, stopped), root / "stopped.log",
                       timeout=give_up, env=env, moment=moment, watch=ckpt)  # fmt: skip
    sent = result["sent"] or (float(stamp.read_text()) if stamp.is_file() else None)
    problems = []
    out = (root / "stopped.log").read_text(errors="replace")
    seconds = None if sent is None else result["ended"] - sent
    code = result["returncode"]
    outcome = "stopped"
    if result["hung"]:
        problems.append(f"the run did not exit: killed {give_up:.0f} s after its start (stacks: stopped.stacks.txt)")
    elif sent is None:
        problems.append("the moment was never reached: no signal was sent")
    elif seconds > bound:
        problems.append(f"the run took {seconds:.1f} s to exit after the signal (bound {bound:.0f} s)")
    elif code != 128 + signal.SIGTERM and moment.timed:
        # a signal from outside can land where the run has no say: before its handlers exist (Python's
        # default ends the process at once; a rank that Lightning is starting dies, and Lightning then
        # kills rank 0) or after its work is done (it ends as it would have)
        if (stopped / "metrics.json").is_file() and code in (0, -signal.SIGTERM):
            outcome = "finished"
            ref, got = (json.loads((d / "metrics.json").read_text()) for d in (reference, stopped))
            differ = differing_metrics(ref, got)
            if differ:
                problems.append(f"the run finished, but with other test metrics: {differ[:4]}")
        elif code in (-signal.SIGTERM, -signal.SIGKILL) and not ckpt.is_file():
            outcome = "ended before the run's handlers"
        else:
            problems.append(f"rank 0 exited with {code}, not {128 + signal.SIGTERM}")
    elif code != 128 + signal.SIGTERM:
        problems.append(f"rank 0 exited with {code}, not {128 + signal.SIGTERM}")
    if outcome == "stopped" and not result["hung"] and "stopped by SIGTERM" not in out.replace("Stopped", "stopped"):
        problems.append("rank 0 did not say where it stopped")
    leftovers = list((stopped / "checkpoints").glob("*.tmp-*")) if (stopped / "checkpoints").is_dir() else []
    if leftovers:
        problems.append(f"temporary files left: {[p.name for p in leftovers]}")
    record = {**asdict(moment), "exit_seconds": seconds, "returncode": code, "outcome": outcome, "checkpoint": False}
    if ckpt.is_file() and outcome == "stopped":
        record["checkpoint"] = True
        try:
            saved = load_checkpoint(ckpt)
            record["global_step"] = int(saved["global_step"])
        except Exception as e:  # noqa: BLE001 - reported, not raised
            problems.append(f"last.ckpt cannot be read: {e}")
        else:
            if f"ckpt_path={ckpt}" not in out:
                problems.append("rank 0 did not name the checkpoint to go on from")
            if not problems:
                resume = run_and_signal(train_argv([f"ckpt_path={ckpt}"], data_dir, resumed), root / "resumed.log",
                                   timeout=600, env=env)  # fmt: skip
                if resume["hung"] or resume["returncode"] != 0:
                    problems.append(f"the resumed run failed ({resume['returncode']}, see resumed.log)")
                else:
                    a, b = final_weights(reference, ckpt), final_weights(resumed, ckpt)
                    if a["global_step"] != b["global_step"]:
                        problems.append(f"resumed run ended at step {b['global_step']}, not {a['global_step']}")
                    for key, value in a["state_dict"].items():
                        if not torch.allclose(b["state_dict"][key], value, rtol=1e-5, atol=1e-6):
                            problems.append(f"resumed weights differ from the uninterrupted run's: {key}")
                            break
                    ref, got = (json.loads((d / "metrics.json").read_text()) for d in (reference, resumed))
                    differ = differing_metrics(ref, got)
                    if differ:
                        problems.append(f"resumed test metrics differ: {differ[:4]}")
    record["problems"] = problems
    return record


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--moments", type=int, default=22, help="how many moments (>= 18 covers every phase twice)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the schedule")
    parser.add_argument("--only", nargs="*", default=None, help="names of the schedule's moments to run")
    parser.add_argument("--bound", type=float, default=60.0, help="seconds a run may take to exit after the signal")
    parser.add_argument("--give-up", type=float, default=None, help="seconds from its start after which a run "
                        "counts as hung (default: bound + 240)")  # fmt: skip
    parser.add_argument("--out", type=Path, default=None, help="folder for the runs (default: a new temporary one)")
    parser.add_argument("--keep", action="store_true", help="keep the runs' folders of moments that passed")
    parser.add_argument("--dry-run", action="store_true", help="print the schedule and the run's command, run nothing")
    args = parser.parse_args(argv)
    if args.dry_run:
        moments = schedule(args.moments, args.seed)
        if args.only is not None:
            moments = [m for m in moments if m.name in args.only]
        print(" ".join(train_argv([], Path("<out>/data"), Path("<out>/<moment>/stopped"))[1:]))
        for i, m in enumerate(moments):
            sender = f"sent by rank {m.rank}" if not m.timed else "sent from outside"
            print(f"{i:2d} {m.name:42s} {m.target:6s} {sender}")
        return 0
    if not Path("src/train.py").is_file():
        parser.error("run it from the repository root (python -m src.train must work there)")
    out = args.out or Path(tempfile.mkdtemp(prefix="preemption-"))
    out.mkdir(parents=True, exist_ok=True)
    if any(out.iterdir()):
        parser.error(f"--out {out} is not empty; name a new folder")
    moments = schedule(args.moments, args.seed)
    if args.only is not None:
        moments = [m for m in moments if m.name in args.only]
    env = {**os.environ, "WANDB_SILENT": "true"}
    data_dir, reference = out / "data", out / "reference" / "run"
    reference.parent.mkdir()
    started = time.monotonic()
    ref = run_and_signal(train_argv([], data_dir, reference), out / "reference" / "run.log", timeout=900, env=env)
    if ref["hung"] or ref["returncode"] != 0:
        print(f"the uninterrupted run failed ({ref['returncode']}): see {out / 'reference' / 'run.log'}")
        return 1
    print(f"uninterrupted run: {time.monotonic() - started:.0f} s; {len(moments)} moments, seed {args.seed}")
    records = []
    for i, moment in enumerate(moments):
        root = out / f"{i:02d}"
        root.mkdir()
        t0 = time.monotonic()
        record = check_moment(moment, root, data_dir, reference, args.bound, env=env, give_up=args.give_up)
        record["seconds"] = round(time.monotonic() - t0, 1)
        records.append(record)
        exit_s = "-" if record["exit_seconds"] is None else f"{record['exit_seconds']:.1f}"
        status = "ok" if not record["problems"] else "FAIL: " + "; ".join(record["problems"])
        if record["outcome"] != "stopped" and not record["problems"]:
            status += f" ({record['outcome']})"
        print(f"{i:2d} {moment.name:42s} exit {exit_s:>5s} s  ckpt {'yes' if record['checkpoint'] else 'no ':3s}  "
              f"{status}", flush=True)  # fmt: skip
        if not record["problems"] and not args.keep:
            shutil.rmtree(root)
    (out / "results.json").write_text(json.dumps(records, indent=2))
    failed = [r for r in records if r["problems"]]
    exits = [r["exit_seconds"] for r in records if r["exit_seconds"] is not None]
    print(f"{len(records) - len(failed)} of {len(records)} moments passed in {time.monotonic() - started:.0f} s; "
          f"slowest exit after the signal {max(exits, default=float('nan')):.1f} s (bound {args.bound:.0f} s); "
          f"results in {out / 'results.json'}")  # fmt: skip
    return len(failed)


if __name__ == "__main__":
    sys.exit(main())
