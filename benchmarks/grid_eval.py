"""Benchmark: fast HEALPix grid evaluation of SO(3) signals vs the dense Wigner matrix.

Compares, per grid level, the fast evaluator :class:`image2sphere.so3.grid_eval.HealpixGridEvaluator`
with the naive dense method ``coeffs @ D.T``,
``D = flat_wigner_from_angles(lmax, *so3_healpix_grid_angles(level))``:

1. operator build time and size (fast operator vs dense ``(N, n_coeffs)`` float32 matrix);
2. full-grid logits, time per image (median of repeats after a warm-up), with an agreement check;
3. log-likelihood normaliser + argmax (``logsumexp_and_max``) vs dense matmul + logsumexp + max;
4. peak RSS increase of the fast calls, measured in fresh subprocesses (Linux: the peak is reset through
   ``/proc/self/clear_refs`` right before the call); the dense path's memory is given analytically.

The dense matrix is built at levels <= 4 only unless ``--dense-level5``: at level 5 it is 4.3 GB and takes
minutes, so its build time and matmul time are extrapolated linearly in N from the largest level where it
was built (marked with "~"). The dense matrix is built with one ``flat_wigner_from_angles`` call per
chunk of at most 294,912 points (one level-4 grid), so levels <= 4 are a single call and a level-5 build
is 8 calls of the level-4 size (a single call at level 5 would need ~28 GB of temporaries).

Usage::

    python benchmarks/grid_eval.py                       # lmax 6, levels 3 4 5, batch 64 (~2-3 min)
    python benchmarks/grid_eval.py --levels 3 4 --repeats 7
    python benchmarks/grid_eval.py --dense-level5        # really build the 4.3 GB matrix (minutes)
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import statistics
import subprocess
import sys
import time

# Before torch's first allocation, as `import image2sphere` would do (see src/image2sphere/__init__.py):
# both methods then get transparent huge pages for their large outputs, instead of first-touch page
# faults dominating (and adding noise to) the full-grid timings.
os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

import torch  # noqa: E402

from _machine import load_line  # noqa: E402  (benchmarks/_machine.py, beside this script)
from image2sphere.so3 import (  # noqa: E402
    flat_wigner_from_angles,
    n_so3_coeffs,
    so3_grid_size,
    so3_healpix_grid_angles,
    so3_healpix_index_to_angles,
)
from image2sphere.so3.grid_eval import MAX_OUTPUT_BYTES, HealpixGridEvaluator  # noqa: E402

DTYPE = torch.float32
BYTES = 4  # float32
DENSE_CHUNK_POINTS = 72 * 8**4  # one flat_wigner_from_angles call per this many grid points
MAX_DENSE_LEVEL = 5  # never build the dense matrix above this level (level 6: 34 GB)
REL_TOL = 1e-4
N_SUBSET = 16384  # grid points of the float64 spot check where the dense matrix is not built


# ---------------------------------------------------------------------------------------------- helpers
def median_time(fn, repeats: int, warmup: int = 1) -> float:
    """Median wall time of ``fn()`` over ``repeats`` runs after ``warmup`` untimed runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def build_dense(lmax: int, level: int) -> tuple[torch.Tensor, float]:
    """Dense float32 Wigner matrix ``(N, n_coeffs)`` of the level-``level`` grid and its build time."""
    t0 = time.perf_counter()
    alpha, beta, gamma = so3_healpix_grid_angles(level, dtype=DTYPE)
    n_points = alpha.shape[0]
    if n_points <= DENSE_CHUNK_POINTS:
        D = flat_wigner_from_angles(lmax, alpha, beta, gamma)
    else:
        D = torch.empty(n_points, n_so3_coeffs(lmax), dtype=DTYPE)
        for i in range(0, n_points, DENSE_CHUNK_POINTS):
            j = i + DENSE_CHUNK_POINTS
            D[i:j] = flat_wigner_from_angles(lmax, alpha[i:j], beta[i:j], gamma[i:j])
    return D, time.perf_counter() - t0


def dense_lse_and_max(coeffs: torch.Tensor, D: torch.Tensor):
    logits = coeffs @ D.T
    vals, idx = logits.max(dim=1)
    return torch.logsumexp(logits, dim=1), vals, idx


def rel_err(a: torch.Tensor, ref: torch.Tensor) -> float:
    ref64 = ref.double()
    return ((a.double() - ref64).abs().max() / ref64.abs().max().clamp_min(1e-30)).item()


def check_line(name: str, err: float) -> str:
    verdict = "OK" if err < REL_TOL else "FAIL"
    return f"  check {name}: max|fast - ref| / max|ref| = {err:.1e}  (< {REL_TOL:.0e}: {verdict})"


def fmt_mb(nbytes: float | None, approx: bool = False) -> str:
    if nbytes is None:
        return "n/a"
    return ("~" if approx else "") + f"{nbytes / 1e6:,.1f}"


def fmt_num(x: float | None, approx: bool = False, digits: int = 3) -> str:
    if x is None:
        return "n/a"
    return ("~" if approx else "") + f"{x:.{digits}g}"


def fmt_ratio(dense: float | None, fast: float | None, approx: bool = False) -> str:
    if dense is None or fast is None or fast <= 0:
        return "n/a"
    return ("~" if approx else "") + f"{dense / fast:,.1f}x"


# ------------------------------------------------------------------------------------ peak memory (child)
def _proc_status_kb(field: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise KeyError(field)


def peak_child(lmax: int, level: int, batch: int, op: str) -> None:
    """Run in a fresh process: build the operator, reset the peak RSS, run ``op`` once, print JSON."""
    ev = HealpixGridEvaluator(lmax, level, dtype=DTYPE)
    coeffs = torch.randn(batch, n_so3_coeffs(lmax), generator=torch.Generator().manual_seed(0))
    gc.collect()
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")  # reset VmHWM (peak RSS) to the current RSS
        rss0 = _proc_status_kb("VmRSS")
    except OSError as exc:
        print(json.dumps({"error": f"cannot reset peak RSS: {exc}"}))
        return
    out = ev.logits(coeffs) if op == "logits" else ev.logsumexp_and_max(coeffs)
    peak = _proc_status_kb("VmHWM")
    del out
    print(json.dumps({"delta_bytes": (peak - rss0) * 1024}))


def measure_peak(lmax: int, level: int, batch: int, op: str, fixed_mmap: bool = False) -> int | None:
    """Peak RSS increase (bytes) of one fast ``op`` call, in a subprocess; ``None`` if not measurable.

    ``fixed_mmap``: run the child with ``MALLOC_MMAP_THRESHOLD_=1 MiB`` so that glibc returns every
    freed large buffer to the OS at once; the peak then reflects the live tensors.
    """
    if not sys.platform.startswith("linux"):
        return None
    cmd = [sys.executable, os.path.abspath(__file__), "--lmax", str(lmax), "--batch", str(batch)]
    cmd += ["--peak-child", str(level), op]
    env = dict(os.environ)
    if fixed_mmap:
        env["MALLOC_MMAP_THRESHOLD_"] = str(2**20)
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    try:
        result = json.loads(res.stdout.strip().splitlines()[-1])
    except (IndexError, json.JSONDecodeError):
        print(f"  (peak-RSS subprocess failed: {res.stderr.strip()[-300:]})")
        return None
    if "error" in result:
        print(f"  ({result['error']})")
        return None
    return result["delta_bytes"]


# ----------------------------------------------------------------------------------------------- main
def bench_level(args, level: int, ref: dict) -> dict:
    lmax, batch = args.lmax, args.batch
    n = n_so3_coeffs(lmax)
    n_pix, n_gamma = so3_grid_size(level)
    N = n_pix * n_gamma
    r: dict = {"level": level, "N": N}
    print(
        f"\n=== level {level}: N = {N:,} grid points ({n_pix:,} pixels x {n_gamma} gammas), "
        f"lmax {lmax} ({n} coeffs), batch {batch}, float32 ==="
    )

    # 1. operator build
    builds = []
    for _ in range(args.build_repeats):
        gc.collect()
        t0 = time.perf_counter()
        ev = HealpixGridEvaluator(lmax, level, dtype=DTYPE)
        builds.append(time.perf_counter() - t0)
    r["fast_build"] = statistics.median(builds)
    r["fast_bytes"] = ev.operator_bytes
    r["dense_bytes"] = N * n * BYTES

    build_dense_here = level <= 4 or (level == 5 and args.dense_level5)
    D = None
    if build_dense_here:
        gc.collect()
        D, r["dense_build"] = build_dense(lmax, level)
        assert D.shape == (N, n) and D.dtype == DTYPE
        r["dense_extrapolated"] = False
    coeffs = torch.randn(batch, n, generator=torch.Generator().manual_seed(level))

    # 2. full-grid logits
    out_bytes = batch * N * BYTES
    if out_bytes <= MAX_OUTPUT_BYTES:
        r["fast_logits"] = median_time(lambda: ev.logits(coeffs), args.repeats) / batch
        fast_logits = ev.logits(coeffs)
    else:
        r["fast_logits"], fast_logits = None, None
        print(f"  fast logits skipped: output {out_bytes / 1e9:.1f} GB > MAX_OUTPUT_BYTES")
    # 3. logsumexp + max + argmax (streamed)
    r["fast_lse"] = median_time(lambda: ev.logsumexp_and_max(coeffs), args.repeats) / batch
    lse_f, max_f, arg_f = ev.logsumexp_and_max(coeffs)

    checks = []
    if D is not None:
        r["dense_logits"] = median_time(lambda: coeffs @ D.T, args.repeats) / batch
        r["dense_lse"] = median_time(lambda: dense_lse_and_max(coeffs, D), args.repeats) / batch
        dense_logits = coeffs @ D.T
        lse_d, max_d, arg_d = dense_lse_and_max(coeffs, D)
        if fast_logits is not None:
            checks.append(check_line("full-grid logits vs dense", rel_err(fast_logits, dense_logits)))
        checks.append(check_line("logsumexp vs dense", rel_err(lse_f, lse_d)))
        checks.append(check_line("max vs dense", rel_err(max_f, max_d)))
        at_fast = dense_logits.gather(1, arg_f[:, None]).squeeze(1)  # dense value at the fast argmax
        same = int((arg_f == arg_d).sum())
        checks.append(f"  check argmax: {same}/{batch} indices identical to the dense argmax")
        checks.append(check_line("dense logit at the fast argmax vs dense max", rel_err(at_fast, max_d)))
        if level >= ref.get("level", -1):  # extrapolate from the largest level where D was built
            ref.update(level=level, N=N, build=r["dense_build"], mm=r["dense_logits"], lse=r["dense_lse"])
        del dense_logits
    else:
        if ref:
            scale = N / ref["N"]
            r["dense_build"] = ref["build"] * scale
            r["dense_logits"] = ref["mm"] * scale
            r["dense_lse"] = ref["lse"] * scale
            r["dense_extrapolated"] = True
            r["ref_level"] = ref["level"]
        # spot check against a float64 dense reference on random grid points
        idx = torch.randint(N, (N_SUBSET,), generator=torch.Generator().manual_seed(1))
        D_sub = flat_wigner_from_angles(lmax, *so3_healpix_index_to_angles(idx, level))  # float64
        ref_sub = coeffs.double() @ D_sub.T
        if fast_logits is not None:
            checks.append(
                check_line(
                    f"logits vs float64 dense on {N_SUBSET:,} random points",
                    rel_err(fast_logits[:, idx], ref_sub),
                )
            )
        max_ref = (
            coeffs.double() @ flat_wigner_from_angles(lmax, *so3_healpix_index_to_angles(arg_f, level)).T
        ).diagonal()
        checks.append(check_line("max vs float64 Wigner at its argmax", rel_err(max_f, max_ref)))
        if fast_logits is not None:
            checks.append(
                check_line("logsumexp vs torch.logsumexp(fast logits)", rel_err(lse_f, fast_logits.logsumexp(1)))
            )
            same = int((arg_f == fast_logits.argmax(1)).sum())
            checks.append(f"  check argmax: {same}/{batch} identical to argmax of fast full-grid logits")
        checks.append("  (dense matrix not built at this level: no full dense comparison)")
    fast_logits = D = ev = None  # free the level's large tensors before the subprocesses
    gc.collect()

    # 4. peak memory (fast: measured in subprocesses; dense: analytic lower bound)
    if not args.no_peak:
        r["peak_fast_lse"] = measure_peak(lmax, level, batch, "lse")
        r["peak_fast_lse_mmap"] = measure_peak(lmax, level, batch, "lse", fixed_mmap=True)
        r["peak_fast_logits"] = measure_peak(lmax, level, batch, "logits") if out_bytes <= MAX_OUTPUT_BYTES else None
    r["dense_working"] = r["dense_bytes"] + out_bytes  # matrix + (B, N) logits, both paths

    print_level_table(r, batch)
    for line in checks:
        print(line)
    return r


def print_level_table(r: dict, batch: int) -> None:
    ex = r.get("dense_extrapolated", False)
    note = f"  (~ = extrapolated linearly in N from level {r['ref_level']})" if ex else ""
    w = 42
    print(f"  {'':{w}}{'fast':>14}{'dense':>16}{'dense/fast':>14}{note}")
    rows = [
        ("operator build time [s]", r["fast_build"], r.get("dense_build"), ex, 3),
        ("operator size [MB]", r["fast_bytes"] / 1e6, r["dense_bytes"] / 1e6, False, 4),
        ("full-grid logits [ms/image]", _ms(r.get("fast_logits")), _ms(r.get("dense_logits")), ex, 3),
        ("logsumexp+max+argmax [ms/image]", _ms(r.get("fast_lse")), _ms(r.get("dense_lse")), ex, 3),
    ]
    for name, f, d, approx, digits in rows:
        print(
            f"  {name:{w}}{fmt_num(f, digits=digits):>14}{fmt_num(d, approx, digits):>16}{fmt_ratio(d, f, approx):>14}"
        )
    if "peak_fast_lse" in r:
        dense = r["dense_working"]
        peak_rows = [
            ("peak RSS incr., lse+argmax [MB] (a)", r["peak_fast_lse"]),
            ("peak RSS incr., lse+argmax [MB] (b)", r["peak_fast_lse_mmap"]),
            ("peak RSS incr., full-grid logits [MB] (a)", r["peak_fast_logits"]),
        ]
        for name, f in peak_rows:
            print(f"  {name:{w}}{fmt_mb(f):>14}{'>= ' + fmt_mb(dense):>16}{fmt_ratio(dense, f):>14}")
        print(
            "    peak RSS increase of one call in a fresh process (fast includes its output; dense: matrix +\n"
            f"    {batch} x N logits, analytic lower bound). (a) default glibc malloc; (b) with\n"
            "    MALLOC_MMAP_THRESHOLD_=1 MiB, so that freed blocks go back to the system at once (live tensors only)"
        )


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else seconds * 1e3


def print_summary(results: list[dict]) -> None:
    print("\n=== dense/fast ratios (higher = fast is better; ~ = dense side extrapolated) ===")
    print(f"  {'level':>5}{'build time':>14}{'operator size':>16}{'logits/image':>16}{'lse+argmax/image':>20}")
    for r in results:
        ex = r.get("dense_extrapolated", False)
        print(
            f"  {r['level']:>5}{fmt_ratio(r.get('dense_build'), r['fast_build'], ex):>14}"
            f"{fmt_ratio(r['dense_bytes'], r['fast_bytes']):>16}"
            f"{fmt_ratio(r.get('dense_logits'), r.get('fast_logits'), ex):>16}"
            f"{fmt_ratio(r.get('dense_lse'), r.get('fast_lse'), ex):>20}"
        )

    by_level = {r["level"]: r for r in results}
    print("\n=== targets ===")

    def verdict(ok: bool) -> str:
        return "MET" if ok else "NOT MET"

    r4 = by_level.get(4)
    if r4 and r4.get("dense_logits") and r4.get("fast_logits"):
        ratio = r4["dense_logits"] / r4["fast_logits"]
        approx = "~" if r4.get("dense_extrapolated") else ""
        print(f"  full-grid logits at level 4 >= 5x faster than dense: {approx}{ratio:.1f}x -> {verdict(ratio >= 5)}")
    else:
        print("  full-grid logits at level 4 >= 5x faster than dense: not evaluated (level 4 not run)")

    top = max(results, key=lambda r: r["level"])
    ratios = ", ".join(f"level {r['level']}: {r['dense_bytes'] / r['fast_bytes']:.1f}x" for r in results)
    size_ratio = top["dense_bytes"] / top["fast_bytes"]
    print(
        f"  operator >= 50x smaller than the dense matrix (at level {top['level']}): {size_ratio:.1f}x "
        f"-> {verdict(size_ratio >= 50)}  [{ratios}]"
    )

    r5 = by_level.get(5)
    if r5:
        t = r5["fast_build"]
        print(f"  level-5 operator built in < 5 s: {t:.2f} s -> {verdict(t < 5)}")
        mm = r5.get("dense_logits")
        if mm is not None:
            how = (
                f"extrapolated from level {r5['ref_level']} per-point matmul cost"
                if r5.get("dense_extrapolated")
                else "measured"
            )
            ok = r5["fast_lse"] < mm
            approx = "~" if r5.get("dense_extrapolated") else ""
            print(
                "  level-5 lse+argmax per image faster than the dense matmul alone: "
                f"fast {r5['fast_lse'] * 1e3:.1f} ms vs dense matmul {approx}{mm * 1e3:.1f} ms ({how}) "
                f"-> {verdict(ok)}"
            )
        else:
            print("  level-5 lse+argmax faster than the dense matmul alone: not evaluated (no dense reference)")
    else:
        print("  level-5 targets: not evaluated (level 5 not run)")


SLOWER = "multi-threaded timings can be several times slower"


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--lmax", type=int, default=6)
    p.add_argument("--levels", type=int, nargs="+", default=[3, 4, 5])
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--repeats", type=int, default=3, help="timed repeats (median) after one warm-up")
    p.add_argument("--build-repeats", type=int, default=3, help="fast operator builds timed (median)")
    p.add_argument("--dense-level5", action="store_true", help="really build the 4.3 GB dense matrix at level 5")
    p.add_argument("--no-peak", action="store_true", help="skip the peak-RSS subprocesses")
    p.add_argument("--peak-child", nargs=2, metavar=("LEVEL", "OP"), help=argparse.SUPPRESS)
    return p.parse_args(argv)


def main(argv=None) -> None:
    args = parse_args(argv)
    if args.peak_child:
        peak_child(args.lmax, int(args.peak_child[0]), args.batch, args.peak_child[1])
        return
    levels = sorted(set(args.levels))
    if any(lv > MAX_DENSE_LEVEL for lv in levels):
        print(f"note: the dense matrix is never built above level {MAX_DENSE_LEVEL}; it is extrapolated there")
    t_start = time.perf_counter()
    print(
        f"image2sphere grid evaluation benchmark: torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads, lmax {args.lmax}, levels {levels}, batch {args.batch}, float32, "
        f"THP_MEM_ALLOC_ENABLE={os.environ.get('THP_MEM_ALLOC_ENABLE')}"
    )
    print(
        f"timings: median of {args.repeats} runs after 1 warm-up "
        f"(fast build: median of {args.build_repeats}; dense build: 1 run); per-image = batch time / batch"
    )
    print(load_line("at start", SLOWER))
    # one-time costs (e3nn init, lazy imports) paid before anything is timed
    HealpixGridEvaluator(args.lmax, 0, dtype=DTYPE)
    build_dense(args.lmax, 0)

    ref: dict = {}
    needs_ref = 4 not in levels and any(lv > 5 or (lv == 5 and not args.dense_level5) for lv in levels)
    if needs_ref:
        print("\n(measuring the dense build and matmul at level 4 only as the reference for extrapolation)")
        D, t_build = build_dense(args.lmax, 4)
        coeffs = torch.randn(args.batch, D.shape[1])
        mm = median_time(lambda: coeffs @ D.T, args.repeats) / args.batch
        lse = median_time(lambda: dense_lse_and_max(coeffs, D), args.repeats) / args.batch
        ref.update(level=4, N=D.shape[0], build=t_build, mm=mm, lse=lse)
        del D
    results = [bench_level(args, level, ref) for level in levels]
    print_summary(results)
    print(f"\ntotal benchmark time: {time.perf_counter() - t_start:.0f} s; {load_line('at end', SLOWER)}")


if __name__ == "__main__":
    main()
