"""Benchmark: the grid evaluation of the SO(3) flow (``model=rotation_flow``) and of IPDF, this checkout
against an earlier revision of the package, measured in one run.

Two measurements, each in a fresh process per source tree (so both trees are imported the same way):

1. **sweep**: ``grid_logsumexp_and_max(--level)`` (the log normaliser and the mode, one pass over the grid)
   for a batch of ``--batch`` images, of the flow with its default size (``conf/model/rotation_flow.yaml``:
   4 blocks, conditioners of 64 hidden units, a condition of 256 numbers) started at random, and of IPDF
   (``conf/model/ipdf.yaml``);
2. **test batch**: what the test loop computes for one batch of the flow (``PoseEstimationModule._evaluate``
   with the recalibration pairs, the exact density and the spread), at ``--eval-level`` with the spread at
   ``--spread-level``: the scenario of a user's ``python -m src.eval`` on a flow checkpoint.

The two trees take turns, ``--repeats`` times; the medians and their ratios are printed, of the wall-clock
time and of the process's CPU time. With ``--threads 1`` the CPU time is the work done, however busy the
machine; with more threads it also counts threads spinning while they wait for each other, and on a machine
whose CPUs other processes share, a tree that runs many short parallel steps (the flow here) waits far more
than one that runs few long ones (the baseline), so the default's ratios there say little. The earlier tree
is ``git archive <--baseline>`` of this repository's ``src/`` in a temporary directory (on ``PYTHONPATH``,
which the editable install then yields to). The default baseline is the revision before the flow's grid
evaluation was made faster.

Measured on this project's 2-core CPU with the defaults (batch 16; this tree against 17e4829), the values the
same to float32 rounding (log normalisers to 1.9e-06, spreads to 1.2e-04 degrees):

* nearly idle (load average 0.5 at the start), torch's 2 threads, two runs: the test batch in 4.65 s and
  4.54 s against 58.1 s (12.5 and 12.8 times as fast), the level-3 sweep 7.7 and 8.1 times as fast (IPDF's,
  not changed since the first speed-up, 1.7 times);
* one thread (``--threads 1``): nearly idle, the test batch 6.95 s against 76.2 s (11.0 times), the sweep 6.1
  times; at a load average of about 4, 10.9 s against 119.5 s (10.9 times);
* torch's 2 threads at a load average of about 4 (another process running the test suite): 2.8 to 4.6 times,
  the flow's test batch taking 52 s to 97 s.

Usage::

    python benchmarks/flow_grid.py                 # about 3 minutes on 2 idle cores (torch's 2 threads)
    python benchmarks/flow_grid.py --threads 1     # steadier where other processes share the CPUs
    python benchmarks/flow_grid.py --level 2 --eval-level 2 --spread-level 2 --repeats 1   # smoke
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BASELINE = "17e4829"  # the last revision with the earlier grid evaluation

# run in a child process, with the tree to measure first on sys.path
MEASURE = r"""
import json, sys, time
import torch
import image2sphere
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from image2sphere.so3.rotations import random_rotations
from image2sphere.training import register_resolvers

level, eval_level, spread_level, batch, threads = map(int, sys.argv[1:6])
conf = sys.argv[6]
if threads:
    torch.set_num_threads(threads)
register_resolvers()
with initialize_config_dir(version_base="1.3", config_dir=conf):
    flow_cfg = compose("train", overrides=["model=rotation_flow", "dataset.image_size=32", "model.net.start=random",
                                            f"eval_grid_level={eval_level}", f"model.spread_grid_level={spread_level}"])
    ipdf_cfg = compose("train", overrides=["model=ipdf", "dataset.image_size=32"])
torch.manual_seed(0)
module = instantiate(flow_cfg.model).eval()
ipdf = instantiate(ipdf_cfg.model.net).eval()
images = torch.randn(batch, 3, 32, 32)
out = {"file": image2sphere.__file__}
with torch.inference_mode():
    for name, net in (("flow", module.net), ("ipdf", ipdf)):
        dist = net.output_distribution(net(images))
        t0, c0 = time.perf_counter(), time.process_time()
        lse = dist.grid_logsumexp_and_max(level)[0]
        out[f"{name} sweep"], out[f"{name} sweep cpu"] = time.perf_counter() - t0, time.process_time() - c0
        out[f"{name} lse"] = lse.tolist()
    test_batch = {"image": images, "class_index": torch.zeros(batch, dtype=torch.long), "index": torch.arange(batch),
                  "rotations": random_rotations(batch, generator=torch.Generator().manual_seed(1))[:, None],
                  "mask": torch.ones(batch, 1, dtype=torch.bool)}
    t0, c0 = time.perf_counter(), time.process_time()
    result = module._evaluate(test_batch, eval_level, spread_level, calibration=True)
    out["flow test batch"], out["flow test batch cpu"] = time.perf_counter() - t0, time.process_time() - c0
    out["flow spread"] = result["spread"].tolist()
print("RESULT " + json.dumps(out))
"""


def measure(src: Path, args) -> dict:
    env = {**os.environ, "PYTHONPATH": str(src), "WANDB_SILENT": "true"}
    argv = [sys.executable, "-c", MEASURE, str(args.level), str(args.eval_level), str(args.spread_level),
            str(args.batch), str(args.threads), str(REPO / "conf")]  # fmt: skip
    proc = subprocess.run(argv, capture_output=True, text=True, env=env, cwd=REPO)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    if proc.returncode != 0 or not lines:
        raise SystemExit(f"the measurement failed in {src}:\n{proc.stderr[-3000:]}")
    return json.loads(lines[-1][len("RESULT ") :])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--baseline", default=BASELINE, help="the git revision to compare with")
    p.add_argument("--level", type=int, default=3, help="grid level of the sweep")
    p.add_argument("--eval-level", type=int, default=4, help="the test batch's grid level (eval_grid_level)")
    p.add_argument("--spread-level", type=int, default=4, help="the test batch's spread level")
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--threads", type=int, default=0, help="torch's threads in the measurements (0: its default)")
    args = p.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _machine import cpu_model, load_line  # benchmarks/_machine.py, beside this script

    print(f"device: {cpu_model()}; {load_line('at the start')}")
    threads = args.threads or "torch's default"
    print(f"batch {args.batch}; sweep at level {args.level}; test batch at level {args.eval_level}, spread at "
          f"level {args.spread_level}; baseline {args.baseline}; threads: {threads}\n")  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        archive = subprocess.run(["git", "archive", args.baseline, "src"], cwd=REPO, capture_output=True)
        if archive.returncode != 0:
            raise SystemExit(f"git archive {args.baseline} failed in {REPO} (a git checkout with that revision is "
                             f"needed): {archive.stderr.decode(errors='replace').strip()}")  # fmt: skip
        subprocess.run(["tar", "-x", "-C", tmp], input=archive.stdout, check=True)
        trees = {"baseline": Path(tmp) / "src", "this checkout": REPO / "src"}
        runs: dict[str, list[dict]] = {name: [] for name in trees}
        for _ in range(args.repeats):
            for name, src in trees.items():
                runs[name].append(measure(src, args))
    keys = ("flow sweep", "ipdf sweep", "flow test batch")
    for clock, suffix in (("wall clock", ""), ("CPU (process)", " cpu")):
        median = {name: {k: statistics.median(r[k + suffix] for r in rs) for k in keys} for name, rs in runs.items()}
        print(f"{clock:18s}{'baseline':>12s}{'this checkout':>16s}{'speed-up':>10s}")
        for k in keys:
            a, b = median["baseline"][k], median["this checkout"][k]
            print(f"{k:18s}{a:11.2f}s{b:15.2f}s{a / b:9.1f}x")
        print()
    first, now = runs["baseline"][0], runs["this checkout"][0]
    print(f"baseline imported from {first['file']}, this checkout from {now['file']}")
    # the same numbers, not only faster: the values agree to float32 rounding
    for k in ("flow lse", "ipdf lse", "flow spread"):
        diff = max(abs(x - y) for x, y in zip(first[k], now[k], strict=True))
        print(f"largest difference of {k}: {diff:.2e}")
    print(f"\n{load_line('at the end')}")


if __name__ == "__main__":
    main()
