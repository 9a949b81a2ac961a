"""Stopping on a signal (image2sphere.training.stop): handlers only record, the ranks decide together.

Quick tier: the handlers, the decision on one process and on two (gloo), Lightning's connector switched
off, and in-process fits of a tiny model stopped from inside the optimizer's step, in an epoch's last
batch (the stop waits for the epoch's end) and in the test. The two-process DDP runs stopped at seeded
moments are in tests/test_scaling.py (slow) and benchmarks/preemption.py (the whole schedule).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time

import lightning.pytorch as pl
import pytest
import torch
from torch import nn
from torch.utils.data import DataLoader, TensorDataset

from conftest import caught, load_script
from image2sphere.testing.commands import group_alive, process_group
from image2sphere.testing.signal_at import SignalAt
from image2sphere.training import stop
from image2sphere.training.checkpoint import AtomicCheckpointIO, EpochCheckpoint, batches_done_in_epoch


def _deliver(signum: int) -> None:
    """Send ``signum`` to this process and let Python run its handler."""
    os.kill(os.getpid(), signum)
    for _ in range(100):  # the handler runs between bytecodes, on the main thread
        time.sleep(0.001)


# ------------------------------------------------------------------ handlers
def test_a_signal_is_only_recorded_and_the_previous_handlers_come_back():
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    with stop.handle_signals():
        assert stop.requested() is None
        _deliver(signal.SIGTERM)  # the default handler would end the process here
        assert stop.requested() == signal.SIGTERM
        _deliver(signal.SIGINT)  # a later, different signal does not replace the first
        assert stop.requested() == signal.SIGTERM
        assert stop.decide() == signal.SIGTERM  # no process group: this process's own request
    assert {s: signal.getsignal(s) for s in before} == before


def test_the_second_ctrl_c_stops_at_once():
    with stop.handle_signals():
        _deliver(signal.SIGINT)
        assert stop.requested() == signal.SIGINT
        with pytest.raises(KeyboardInterrupt):
            _deliver(signal.SIGINT)


def test_after_a_second_ctrl_c_one_line_says_what_was_kept_and_the_status_is_130(tmp_path, capsys):
    with stop.handle_signals():
        _deliver(signal.SIGINT)
        interrupt = caught(lambda: _deliver(signal.SIGINT))
        lightning = caught(_exit_as_lightning_does, interrupt)  # its sys.exit(1) while handling it
        assert stop.stopped_at_once(interrupt) and stop.stopped_at_once(lightning)
        assert not stop.stopped_at_once(SystemExit(1))  # an exit without a Ctrl-C behind it
        empty, kept = tmp_path / "empty" / "checkpoints", tmp_path / "kept" / "checkpoints"
        empty.mkdir(parents=True)
        kept.mkdir(parents=True)
        (kept / "last.ckpt").write_bytes(b"x")
        for checkpoint, resumed, folder in ((None, None, empty), (None, "a/last.ckpt", None), (kept / "last.ckpt", None,
                                            kept)):  # fmt: skip
            ended = caught(stop.exit_at_once, "in epoch 1 (step 3)", checkpoint and str(checkpoint), resumed,
                                 folder and str(folder))  # fmt: skip
            assert isinstance(ended, SystemExit) and ended.code == 130
    assert not empty.exists() and (kept / "last.ckpt").is_file()  # only an empty folder is removed
    with stop.handle_signals():
        assert not stop.stopped_at_once(KeyboardInterrupt())  # not the run's: no two Ctrl-C
    start = "Stopped at once by a second Ctrl-C in epoch 1 (step 3): nothing more was saved; "
    assert capsys.readouterr().err.splitlines() == [
        start + "this run wrote no checkpoint",
        start + "this run wrote no checkpoint (resume again from a/last.ckpt: python -m src.train "
        "ckpt_path=a/last.ckpt)",
        start + f"the last checkpoint is {kept / 'last.ckpt'} (resume with python -m src.train "
        f"ckpt_path={kept / 'last.ckpt'})",
    ]


def _exit_as_lightning_does(interrupt: BaseException) -> None:
    try:
        raise interrupt
    except KeyboardInterrupt:
        sys.exit(1)


def test_nothing_requested_decides_nothing_and_a_new_block_forgets_the_last_request():
    with stop.handle_signals():
        _deliver(signal.SIGTERM)
    with stop.handle_signals():
        assert stop.requested() is None and stop.decide() is None


def test_the_requeue_signal_is_recorded_and_its_handler_restored():
    before = signal.getsignal(signal.SIGUSR1)
    with stop.handle_signals(requeue_signals=[signal.SIGUSR1]):
        _deliver(signal.SIGUSR1)
        assert stop.decide() == signal.SIGUSR1
    assert signal.getsignal(signal.SIGUSR1) is before
    with stop.handle_signals():  # requeueing off (not under SLURM): SIGUSR1 is not the run's
        assert signal.getsignal(signal.SIGUSR1) is before


WORKER_SCRIPT = """
import os, subprocess, sys, time
import torch
from torch.utils.data import DataLoader, Dataset
from image2sphere.data.workers import init_worker

class Slow(Dataset):
    def __len__(self):
        return 1000
    def __getitem__(self, i):
        time.sleep(0.005)
        return torch.tensor([i])

loader = DataLoader(Slow(), batch_size=2, num_workers=1, persistent_workers=True, worker_init_fn=init_worker)
it = iter(loader)
next(it)
(worker,) = [w.pid for w in it._workers]
print("worker", worker, flush=True)
subprocess.run(["kill", "-TERM", str(worker)], check=True)  # from another process: left to the rank
subprocess.run(["kill", "-INT", str(worker)], check=True)
time.sleep(0.5)
batches = [next(it)[0, 0].item() for _ in range(5)]
print("served", batches, flush=True)
# the script ends with the persistent worker alive: Python's multiprocessing terminates it at exit (SIGTERM
# from this process), which the worker must obey, or this process waits for it for ever
"""


@pytest.mark.slow
def test_loader_workers_ignore_a_signal_from_outside_and_obey_their_ranks_terminate():
    import subprocess

    with process_group([sys.executable, "-c", WORKER_SCRIPT], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                       text=True) as proc:  # fmt: skip
        out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err[-3000:]
    worker = int(out.split("worker ")[1].split()[0])
    assert "served [2, 4, 6, 8, 10]" in out, out + err[-2000:]  # the worker lived on after SIGTERM and SIGINT
    assert not group_alive(proc.pid) and not os.path.exists(f"/proc/{worker}/stat")


# ------------------------------------------------------------------ the decision on two processes (gloo)
def _two_ranks(script: str, *args: str, timeout: float = 180, env: dict | None = None) -> list:
    """Run ``script`` as ranks 0 and 1 of a gloo group (``sys.argv``: rank, port, ``args``), with PyTorch's
    collective desync check on (``TORCH_DISTRIBUTED_DEBUG=DETAIL``); ``[(returncode, stdout, stderr,
    seconds)]`` per rank, nothing left running whatever happens."""
    import subprocess

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "TORCH_DISTRIBUTED_DEBUG": "DETAIL", **(env or {})}
    start = time.monotonic()
    procs = [subprocess.Popen([sys.executable, "-c", script, str(r), str(port), *args], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, start_new_session=True, env=env)
             for r in (0, 1)]  # fmt: skip
    results = []
    try:
        for p in procs:
            out, err = p.communicate(timeout=timeout)
            results.append((p.returncode, out, err, time.monotonic() - start))
    finally:
        for p in procs:  # nothing left behind, whatever happened
            if group_alive(p.pid):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    return results


RANK_SCRIPT = """
import json, os, signal, sys, time
import torch
from image2sphere.training import stop
rank, port, rounds = int(sys.argv[1]), sys.argv[2], json.loads(sys.argv[3])
torch.distributed.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=2)
decided = []
for requests in rounds:  # one round per entry: each rank's signals, in order
    with stop.handle_signals(requeue_signals=[signal.SIGUSR1]):
        for signum in requests[rank]:
            os.kill(os.getpid(), signum)
            time.sleep(0.05)
        decided.append(stop.decide())
stop.close_decisions()
torch.distributed.destroy_process_group()
print(json.dumps(decided))
"""


@pytest.mark.slow
def test_every_rank_decides_the_strongest_request_of_any_rank():
    """Rank 0 alone asked, rank 1 alone asked, nobody, two different signals on two ranks (the requeue signal
    wins over SIGTERM, SIGTERM over Ctrl-C) and the same two on one rank: every rank comes to the same
    answer each time, and one rank with SIGTERM then the requeue signal decides as two ranks with one each."""
    import json

    T, I, U = int(signal.SIGTERM), int(signal.SIGINT), int(signal.SIGUSR1)
    rounds = [([T], []), ([], [T]), ([], []), ([T], [U]), ([I], [T]), ([T, U], [])]
    results = _two_ranks(RANK_SCRIPT, json.dumps(rounds))
    assert [r[0] for r in results] == [0, 0], [r[2][-2000:] for r in results]
    assert json.loads(results[0][1]) == json.loads(results[1][1]) == [T, T, None, U, T, U]


DECISION_SCRIPT = """
import datetime, json, os, signal, sys, time
from types import SimpleNamespace
import torch
import torch.distributed as dist
from image2sphere.training import stop
rank, port = int(sys.argv[1]), sys.argv[2]
dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=2,
                        timeout=datetime.timedelta(seconds=20))
trainer = SimpleNamespace(strategy=SimpleNamespace(_timeout=datetime.timedelta(seconds=3)))
stop.open_decisions(trainer)  # as Lightning's setup does, at the same point on both ranks
decided = []
with stop.handle_signals():
    for epoch in range(3):
        metric = torch.ones(1)
        # the model's group: a metric that rank 0 syncs before the epoch's end (its progress bar) and the
        # other rank after it (its logger), as Lightning's lazily computed epoch metrics are
        if rank == 0:
            dist.barrier()
            dist.all_reduce(metric)
        if rank == 1 and epoch == 1:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
        stop.decide(trainer, read="none", where=f"the end of epoch {epoch}")
        if rank == 1:
            time.sleep(0.5)  # the other rank reaches its next point long before this one
            dist.barrier()
            dist.all_reduce(metric)
        dist.all_reduce(torch.ones(3))  # the next training step's gradients
        decided.append(stop.decide(trainer, read="earlier", where=f"after batch 0 of epoch {epoch + 1}"))
    print(json.dumps(decided), flush=True)
    # a point that one rank never reaches: the other's decision ends with an error naming it
    start = time.monotonic()
    if rank == 0:
        try:
            stop.decide(trainer, read="all", where="the point rank 1 skips")
        except stop.DecisionTimeout as e:
            print(f"timeout after {time.monotonic() - start:.1f} s: {e}", flush=True)
    else:
        time.sleep(8)
os._exit(0)
"""


@pytest.mark.slow
def test_decisions_never_meet_the_models_collectives_and_a_missing_rank_is_an_error():
    """The ranks' decisions run on a group of their own: a metric synced on rank 0 before an epoch's end and
    on rank 1 after it (what hung a DDP run with the progress bar on) meets its twin, the decision of the
    epoch in which rank 1 was signalled comes at the next epoch's first batch on both ranks, and a point
    that one rank never reaches ends the other's wait within the group's timeout (3 s), naming the point,
    with PyTorch's desync check on."""
    import json

    results = _two_ranks(DECISION_SCRIPT, timeout=120)
    assert [r[0] for r in results] == [0, 0], [r[2][-3000:] for r in results]
    T = int(signal.SIGTERM)
    decided = [json.loads(r[1].splitlines()[0]) for r in results]
    assert decided[0] == decided[1] == [None, T, T]  # a request stays once made
    line = results[0][1].splitlines()[1]
    assert "timeout after" in line and "the point rank 1 skips" in line and "trainer.strategy.timeout" in line
    assert float(line.split("timeout after ")[1].split(" s")[0]) < 15


HANG_SCRIPT = """
import datetime, os, sys, time
import torch
import torch.distributed as dist
from image2sphere.training import stop
rank, port = int(sys.argv[1]), sys.argv[2]
dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=2,
                        timeout=datetime.timedelta(seconds=120))
if rank == 0:
    with stop.handle_signals(grace=3):
        print("waiting", flush=True)
        dist.barrier()  # rank 1 never comes: no Python code runs here until the group's timeout
else:
    time.sleep(60)
"""


@pytest.mark.slow
def test_a_sigterm_during_a_hung_collective_ends_the_process_within_the_grace():
    """Rank 0 waits in a barrier that rank 1 never joins (for the group's 120 s timeout); a SIGTERM cannot be
    handled there, yet the process ends 3 s after it (stop_grace_s) with 143 and every thread's stack."""
    import subprocess
    import threading

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "TORCH_DISTRIBUTED_DEBUG": "DETAIL"}
    procs = [subprocess.Popen([sys.executable, "-c", HANG_SCRIPT, str(r), str(port)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, start_new_session=True, env=env)
             for r in (0, 1)]  # fmt: skip
    try:
        assert procs[0].stdout.readline().strip() == "waiting"
        time.sleep(1.0)  # inside the barrier
        sent = time.monotonic()
        procs[0].send_signal(signal.SIGTERM)
        timer = threading.Timer(60, procs[0].kill)  # only if the watchdog failed
        timer.start()
        _, err = procs[0].communicate()
        timer.cancel()
        seconds = time.monotonic() - sent
    finally:
        for p in procs:
            if group_alive(p.pid):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    assert procs[0].returncode == 128 + signal.SIGTERM, err[-3000:]
    assert 2.5 < seconds < 15, seconds
    assert "SIGTERM was received 3 s ago" in err and "stop_grace_s" in err
    assert "barrier" in err  # where the main thread was


AFTER_A_STOP = """
import atexit, os, signal, sys, time
from image2sphere.training import stop
caught = sys.argv[1] == "caught"
if not caught:
    atexit.register(time.sleep, 600)  # an exit function that never returns (as one joining a stuck worker)
try:
    with stop.handle_signals(grace=2):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.2)
        raise SystemExit(128 + signal.SIGTERM)  # what a decided stop raises
except SystemExit:
    if not caught:
        raise
print("caught", flush=True)
time.sleep(4)  # past the grace: a program that caught the stop goes on
print("alive", flush=True)
"""


@pytest.mark.slow
def test_after_a_stop_a_hung_exit_ends_within_the_grace_and_a_caught_one_goes_on():
    """A stop ends its block with SystemExit. A process that then hangs on its way out (an exit function
    that never returns) still ends 2 s after the signal (stop_grace_s), with 143; a program that catches the
    SystemExit (a test harness running the entry point in-process, IPython's %run) is not ended later."""
    import subprocess

    procs = {case: subprocess.Popen([sys.executable, "-c", AFTER_A_STOP, case], stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True, start_new_session=True)
             for case in ("exiting", "caught")}  # fmt: skip
    started = time.monotonic()
    try:
        results = {case: p.communicate(timeout=120) for case, p in procs.items()}
        seconds = time.monotonic() - started  # both started together; each imports torch and Lightning
    finally:
        for p in procs.values():
            if group_alive(p.pid):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    out, err = results["caught"]
    assert procs["caught"].returncode == 0 and out.split() == ["caught", "alive"], err[-3000:]
    out, err = results["exiting"]
    assert procs["exiting"].returncode == 128 + signal.SIGTERM, err[-3000:]
    assert "SIGTERM was received 2 s ago" in err and "stop_grace_s" in err
    assert seconds < 100, seconds  # not the exit function's 600 s


# ------------------------------------------------------------------ Lightning's own handling switched off
def test_lightning_installs_no_handler_and_never_stops_one_rank_by_itself():
    trainer = pl.Trainer(accelerator="cpu", logger=False, enable_checkpointing=False, enable_progress_bar=False)
    stop.use_flag_only_signals(trainer)
    stop.use_flag_only_signals(trainer)  # idempotent
    assert sum(isinstance(c, stop.StopOnRequest) for c in trainer.callbacks) == 1
    before = signal.getsignal(signal.SIGTERM)
    trainer._signal_connector.register_signal_handlers()
    assert signal.getsignal(signal.SIGTERM) is before
    with stop.handle_signals():
        _deliver(signal.SIGTERM)
        assert not trainer.received_sigterm  # Lightning's loops check this flag on each rank alone
    trainer._signal_connector.teardown()
    assert signal.getsignal(signal.SIGTERM) is before


# ------------------------------------------------------------------ in-process fits stopped by a signal
class _Tiny(pl.LightningModule):
    def __init__(self):
        super().__init__()
        self.layer = nn.Linear(4, 1)
        self.validated = 0

    def training_step(self, batch, batch_idx):
        return self.layer(batch[0]).pow(2).mean()

    def validation_step(self, batch, batch_idx):
        self.validated += 1

    def test_step(self, batch, batch_idx):
        pass

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


def _fit(tmp_path, moment: SignalAt, max_epochs: int = 2, requeue_signals=()):
    data = DataLoader(TensorDataset(torch.randn(16, 4)), batch_size=4)  # 4 batches an epoch
    checkpoint = EpochCheckpoint(dirpath=tmp_path / "checkpoints", save_last=True, save_top_k=0)
    trainer = pl.Trainer(max_epochs=max_epochs, callbacks=[checkpoint, moment], plugins=[AtomicCheckpointIO()],
                         accelerator="cpu", logger=False, enable_progress_bar=False, enable_model_summary=False,
                         num_sanity_val_steps=0, default_root_dir=tmp_path)  # fmt: skip
    stop.use_flag_only_signals(trainer)
    module = _Tiny()
    with stop.handle_signals(requeue_signals):
        with pytest.raises(stop.TrainingInterrupted) as stopped:
            trainer.fit(module, data, data)
    return stopped.value, module


def test_sigterm_inside_the_optimizer_step_stops_after_that_batch_with_its_checkpoint(tmp_path):
    e, _ = _fit(tmp_path, SignalAt("optimizer_step", occurrence=6))  # epoch 1, its second batch
    assert e.signum == signal.SIGTERM and e.epoch == 1 and e.step == 6
    saved = torch.load(e.checkpoint, weights_only=True)
    assert saved["global_step"] == 6 and batches_done_in_epoch(saved) == 2


def test_sigterm_in_an_epochs_last_batch_stops_after_its_validation_and_the_next_batch(tmp_path):
    """An epoch's end only sends its request (a stop there would write last.ckpt while ranks may differ in
    the metrics Lightning has synced): the stop comes after the next epoch's first batch."""
    e, module = _fit(tmp_path, SignalAt("forward_backward", occurrence=4))  # epoch 0's last batch
    assert e.epoch == 1 and e.step == 5
    assert module.validated == 4  # epoch 0's validation ran before the stop
    saved = torch.load(e.checkpoint, weights_only=True)
    assert saved["global_step"] == 5 and batches_done_in_epoch(saved) == 1  # resumes within epoch 1


def test_one_process_keeps_its_strongest_request_as_the_ranks_combine_theirs():
    """SIGTERM then the requeue signal on one rank decides as the two signals on two ranks do: requeue."""
    with stop.handle_signals(requeue_signals=[signal.SIGUSR1]):
        _deliver(signal.SIGTERM)
        _deliver(signal.SIGUSR1)
        assert stop.requested() == signal.SIGUSR1 and stop.decide() == signal.SIGUSR1
        _deliver(signal.SIGTERM)  # weaker than what is recorded: kept as it was
        assert stop.requested() == signal.SIGUSR1


def test_a_nested_block_keeps_the_outer_request_and_handlers():
    before = signal.getsignal(signal.SIGUSR2)
    with stop.handle_signals():
        outer = signal.getsignal(signal.SIGTERM)
        _deliver(signal.SIGTERM)
        with stop.handle_signals(requeue_signals=[signal.SIGUSR2]):
            assert stop.requested() == signal.SIGTERM  # not forgotten by the inner block
            _deliver(signal.SIGUSR2)
            assert stop.decide() == signal.SIGUSR2
        assert signal.getsignal(signal.SIGUSR2) is before  # the inner block's own signal given back
        assert signal.getsignal(signal.SIGTERM) is outer  # the outer block still handles SIGTERM
        assert stop.requested() == signal.SIGUSR2
    assert signal.getsignal(signal.SIGTERM) is not outer


def test_decide_refuses_an_unknown_read_mode():
    with pytest.raises(ValueError, match="read must be one of all, earlier, none"):
        stop.decide(read="later")
    with pytest.raises(ValueError, match="stop_grace_s"):
        with stop.handle_signals(grace=0):
            pass


def test_submitits_requeue_handler_runs_after_last_ckpt_is_written_not_inside_the_step(tmp_path):
    """hydra/launcher=slurm: submitit handles SIGUSR2 (it requeues the job and ends the process). The run
    records the signal like any other, writes last.ckpt at the end of the batch, then calls submitit's
    handler in ordinary code."""
    calls = []
    last = tmp_path / "checkpoints" / "last.ckpt"

    def submitit_like(signum, frame):
        calls.append((signum, last.is_file(), torch.load(last, weights_only=True)["global_step"]))

    previous = signal.signal(signal.SIGUSR2, submitit_like)
    try:
        assert signal.SIGUSR2 in stop.requeue_signals()
        moment = SignalAt("optimizer_step", occurrence=6, signum=signal.SIGUSR2)
        e, _ = _fit(tmp_path, moment, requeue_signals=stop.requeue_signals())
        assert signal.getsignal(signal.SIGUSR2) is submitit_like  # given back after the run
    finally:
        signal.signal(signal.SIGUSR2, previous)
    assert e.signum == signal.SIGUSR2 and e.requeued and e.step == 6
    assert calls == [(signal.SIGUSR2, True, 6)]  # once, after the checkpoint of that very batch


def test_sigterm_before_training_starts_stops_with_no_checkpoint(tmp_path):
    e, _ = _fit(tmp_path, SignalAt("fit_start"))
    assert e.checkpoint is None and e.step == 0
    assert not (tmp_path / "checkpoints").exists() or not any((tmp_path / "checkpoints").iterdir())


def test_sigterm_in_the_test_stops_it_after_that_batch(tmp_path):
    data = DataLoader(TensorDataset(torch.randn(16, 4)), batch_size=4)
    trainer = pl.Trainer(accelerator="cpu", logger=False, enable_progress_bar=False, enable_model_summary=False,
                         callbacks=[SignalAt("test", occurrence=2)])  # fmt: skip
    stop.use_flag_only_signals(trainer)
    with stop.handle_signals(), pytest.raises(stop.StopRequested, match="SIGTERM in the test"):
        trainer.test(_Tiny(), data)
    assert trainer.test_loop.batch_progress.current.completed == 1  # the second batch did not complete


# ------------------------------------------------------------------ the stress check's schedule and tools
def test_the_schedule_covers_every_phase_for_both_targets_and_is_seeded():
    """Quick. The schedule of ``benchmarks/preemption.py`` (its functions, the script read without running it)."""
    tool = load_script("benchmarks/preemption.py")
    schedule, MOMENT_PHASES = tool["schedule"], tool["MOMENT_PHASES"]  # noqa: N806 - the script's names
    moments = schedule(22, seed=0)
    assert len(moments) == 22 and len({m.name for m in moments}) == 22
    covered = {(m.phase, m.target) for m in moments if not m.timed}
    assert covered == {(p, t) for p in MOMENT_PHASES for t in ("rank0", "group")}
    assert sum(m.timed for m in moments) == 4
    for m in moments:
        if not m.timed:
            count, ranks = MOMENT_PHASES[m.phase]
            assert 1 <= m.occurrence <= count and m.rank in ranks
    assert [m.name for m in schedule(22, seed=0)] == [m.name for m in moments]
    assert [m.name for m in schedule(22, seed=1)] != [m.name for m in moments]


def test_group_alive_sees_a_running_group_and_not_an_ended_one():
    import subprocess

    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"], start_new_session=True)
    try:
        assert group_alive(proc.pid) == [proc.pid]
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert group_alive(proc.pid) == []


@pytest.mark.slow
def test_a_second_ctrl_c_exits_130_with_one_last_line_naming_the_checkpoint(tmp_path):
    """Two SIGINTs in the first batch of epoch 1 (the run's own callbacks send them, 3 batches per epoch): the
    second stops at once, inside that batch. Exit status 130; after wandb's closing lines (offline, not silenced)
    the last line says where it stopped and names epoch 0's last.ckpt; nothing else was written."""
    from conftest import ENV, REPO, train_command

    run = tmp_path / "run"
    send = [f"+callbacks.{name}.{key}={value}" for name, phase in (("first", "forward_backward"),
            ("second", "optimizer_step")) for key, value in (("_target_", "image2sphere.testing.signal_at.SignalAt"),
            ("phase", phase), ("occurrence", 4), ("signum", int(signal.SIGINT)))]  # fmt: skip
    cmd = train_command(["trainer.max_epochs=2", *send, f"hydra.run.dir={run}"], tmp_path / "data", tmp_path / "logs")
    env = {k: v for k, v in ENV.items() if k != "WANDB_SILENT"}
    with process_group(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        out, err = proc.communicate(timeout=600)
    last = run / "checkpoints" / "last.ckpt"
    assert proc.returncode == 130, err[-3000:]
    assert err.splitlines()[-1] == (
        "Stopped at once by a second Ctrl-C in epoch 1 (step 3): nothing more was saved; the last checkpoint is "
        f"{last} (resume with python -m src.train ckpt_path={last})"
    ), err[-3000:]
    # wandb finished before the line (its one closing line for an offline run), with no escape codes around it
    assert err.splitlines()[-2].startswith("wandb: offline run saved in "), err[-3000:]
    assert not [line for line in (out + err).splitlines() if "wandb" in line and "\x1b" in line]
    assert sorted(p.name for p in last.parent.iterdir()) == ["last.ckpt"]
    assert torch.load(last, map_location="cpu", weights_only=True)["global_step"] == 3  # epoch 0's end
    assert not (run / "metrics.json").exists()
