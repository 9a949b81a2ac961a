"""``python -m src.tables RUN_DIR [RUN_DIR ...]``: the paper's tables, or a table of any sweep, from finished runs.

Reads every run directory at or below the given directories (each run's ``metrics.json`` and
``.hydra/``). Runs launched for one of the paper's tables (``table=tableN``; or the tables named with
``--table``) fill that table's layout beside the paper's published numbers, as Markdown (printed, and
``<out>/<table>.md``), LaTeX (``<out>/<table>.tex``) and, for the tables that have one, a figure
(``<out>/<table>.png``). Any other sweep (``python -m src.train -m ...``, an Optuna study) gives one
table with a row per setting, the overrides that differ between its runs as columns and the headline
metrics over seeds (``<out>/sweep.md``, ``<out>/sweep.tex``; :mod:`image2sphere.reporting.sweep_table`).

Runs with metrics that did not train or test as configured (``fast_dev_run``, ``limit_test_batches``, stopped
before ``trainer.max_epochs``: :func:`image2sphere.reporting.runs.incomplete_reason`) are listed, not counted,
unless ``--include-unfinished``. The table is printed on every call, so that running the command again is how
one looks at it; its files are only written where they are missing, and an existing file that differs is
named and left as it is unless ``--force`` (:func:`settle_files`). See ``--help``.
"""

import argparse
import os
import sys
import tempfile
from pathlib import Path

import image2sphere  # noqa: F401  (the torchvision guard, before anything imports torchvision)
from image2sphere.reporting import (
    build_sweep_table,
    build_table,
    counted_runs,
    draw_figure,
    find_runs,
    is_sweep,
    load_layouts,
    sweep_header,
    sweep_lines,
    sweep_to_latex,
    sweep_to_markdown,
    to_latex,
    to_markdown,
)
from image2sphere.reporting.sweep_table import SWEEP_NAME

EPILOG = """\
examples:
  python -m src.train table=table7 encoder.weights=IMAGENET1K_V2        # the runs of Table 7
  python -m src.tables logs/table7/multiruns/<date>_<time>_<pid>        # Table 7 next to the paper's
  python -m src.tables logs/table1/multiruns/<sweep> --table table5     # Table 5 from Table 1's runs
  python -m src.tables logs/table7/multiruns/<a> logs/table7/multiruns/<b>   # pool two sweeps (seeds)
  python -m src.tables <small sweep on the built-in data> --dataset symsol_rendered
  python -m src.train -m lmax=2,4 seed=0,1                              # a sweep of your own
  python -m src.tables logs/train/multiruns/<date>_<time>_<pid>         # its table: one row per setting

Paper tables: each cell is the mean over the matching finished runs (seeds), +- their sample standard
deviation; under it the paper's number and the difference (ours - paper). A cell without a run is
shown as a missing cell, never as 0; "n/a" is a metric the method does not have (a point estimate's
log likelihood).

Any other sweep (no run launched with table=<name>, no --table): one row per setting, the overrides of
.hydra/overrides.yaml that differ between the runs as columns (seed left out: the seeds are averaged),
each headline metric of metrics.json as mean +- sample standard deviation over the row's runs, and the
number of runs; written to <out>/sweep.md and sweep.tex. An Optuna study's trials
(hparams_search=optuna_i2s) are ordered by its objective (optimized_metric), best first.

A resumed run (python -m src.train ckpt_path=<run>/checkpoints/last.ckpt ...) is read as what it trained:
its resumed_config.yaml, the group choices and overrides of the run that wrote the checkpoint, and the
resume's own overrides that changed a value (ckpt_path is no column).

Which runs count: a run counts when it wrote metrics.json and trained and tested as configured. These
runs have metrics but are left out of the means, listed below the table as "not counted: <dir> (why)":
  fast_dev_run                      trainer.fast_dev_run (one batch of each loop: a smoke test)
  limit_test_batches=N: ...         tested on part of the test set (an integer, or a fraction below 1.0)
  unfinished: stopped after epoch E of N
                                    a run that trained (train=true) whose checkpoints/last.ckpt has fewer
                                    epochs than trainer.max_epochs of its config (a resumed run's
                                    resumed_config.yaml) and fewer steps than a trainer.max_steps it sets
                                    (e.g. ended by trainer.max_time)
--include-unfinished counts them, marked: "N (k unfinished)" runs in a sweep's table, "ours (N runs,
k unfinished)" in a paper's, and "counted although unfinished: <dir>" below. limit_train_batches and
limit_val_batches are a training budget like max_epochs: such a run that trained to its end counts. A
train=false run only tests a checkpoint and is never unfinished; a run without checkpoints/last.ckpt
counts (nothing says it stopped early). Run directories without metrics.json are listed as not finished.

Files: the table is always printed. <out>/<table>.md, .tex (and .png) are written when they do not exist
yet; when they exist with the same content nothing is written (one line says so); when they exist and
differ (runs have finished or changed since), one line names them and nothing is written: --force replaces
them, --out <folder> writes elsewhere. An existing file is never replaced without --force.
"""


def parse_args(argv: list[str] | None = None, layouts: dict | None = None) -> argparse.Namespace:
    layouts = load_layouts() if layouts is None else layouts
    parser = argparse.ArgumentParser(
        prog="python -m src.tables",
        description="Print and write the I2S paper's tables from finished runs, beside the published numbers, "
        "or a table of any other sweep (one row per setting).",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "run_dirs", nargs="+", metavar="RUN_DIR",
        help="run or sweep directories (e.g. logs/table7/multiruns/<date>_<time>_<pid>); "
        "every run at or below them is read",
    )  # fmt: skip
    parser.add_argument(
        "--table", action="append", choices=sorted(layouts), metavar="NAME",
        help=f"table(s) to write ({', '.join(sorted(layouts))}); default: the table=... the runs were launched with, "
        "or, for runs launched without one, a table of the sweep (sweep.md)",
    )  # fmt: skip
    parser.add_argument(
        "--dataset", default=None,
        help="match runs on this dataset instead of the paper's (e.g. symsol_rendered for a small run on the built-in "
        "data); the published numbers are then not comparable, and the table says so",
    )  # fmt: skip
    parser.add_argument(
        "--out", type=Path, default=None,
        help="folder for <table>.md/.tex/.png or sweep.md/.tex (default: <first RUN_DIR>/tables)",
    )  # fmt: skip
    parser.add_argument(
        "--force", action="store_true",
        help="replace output files that exist and differ from this table (without it they are left as they are)",
    )  # fmt: skip
    parser.add_argument(
        "--include-unfinished", action="store_true",
        help="count the runs with metrics that did not train or test as configured (fast_dev_run, limit_test_batches, "
        "stopped before trainer.max_epochs), marked; by default they are listed below the table, not counted",
    )  # fmt: skip
    parser.add_argument(
        "--wandb-project", nargs="?", const="", default=None, metavar="PROJECT",
        help="also log each table (and its figure) to wandb: to PROJECT, or without a value to the project the "
        "runs logged to (their logger.wandb.project)",
    )  # fmt: skip
    parser.add_argument("--wandb-entity", default=None, help="wandb entity (team) of --wandb-project")
    parser.add_argument(
        "--wandb-mode", choices=("offline", "online"), default="offline",
        help="offline (default: written under <out>/wandb, upload later with `wandb sync`) or online",
    )  # fmt: skip
    return parser.parse_args(argv)


def _push_to_wandb(
    args: argparse.Namespace, name: str, runs: list, columns: list[str], data: list[list[str]], markdown: str,
    figure: Path | None, out: Path, job_type: str,
) -> None:  # fmt: skip
    import wandb

    project, entity = args.wandb_project, args.wandb_entity
    if not project:  # the sweep's own project: where its runs logged
        projects = {r.get("logger.wandb.project", None) for r in runs} - {None}
        project = sorted(projects)[0] if len(projects) == 1 else "image2sphere"
        entities = {r.get("logger.wandb.entity", None) for r in runs} - {None}
        entity = entity or (sorted(entities)[0] if len(entities) == 1 else None)
    run = wandb.init(
        project=project, entity=entity, mode=args.wandb_mode, dir=str(out), job_type=job_type, name=name,
        config={"table": name, "runs": [str(r.path) for r in runs]},
    )  # fmt: skip
    log = {name: wandb.Table(columns=columns, data=data), f"{name}_markdown": wandb.Html(f"<pre>{markdown}</pre>")}
    if figure is not None:
        log[f"{name}_figure"] = wandb.Image(str(figure))
    run.log(log)
    run.finish()


def _push_paper_table(args: argparse.Namespace, filled, markdown: str, figure: Path | None, out: Path) -> None:
    from image2sphere.reporting.tables import MISSING_MD, table_lines

    columns = ["method", "source"] + [
        c["title"] if not c.get("group") else f"{c['group']}: {c['title']}" for c in filled.layout["columns"]
    ]
    data = [[label, source, *cells] for label, source, cells in table_lines(filled, MISSING_MD, "±")]
    _push_to_wandb(args, filled.name, filled.used, columns, data, markdown, figure, out, "paper-table")


def _names(paths: list[Path]) -> str:
    return ", ".join(str(p) for p in paths)


def _write(path: Path, data: bytes, replace: bool) -> None:
    """``data`` into ``path``: a new file (never over one that appeared meanwhile), or the replacement of an
    existing one through a temporary file renamed over it (a reader never sees it half written)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if not replace:
        with open(path, "xb") as f:
            f.write(data)
        return
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, path.stat().st_mode & 0o777)  # the permissions of the file it replaces
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def settle_files(outputs: dict[Path, bytes], force: bool) -> None:
    """Write the table's files as the rules of ``--help`` say, and print one line per outcome: the files
    written, those already up to date, or (without ``force``) those out of date, then nothing is written."""
    existing = {p: p.read_bytes() for p in outputs if p.is_file()}
    stale = [p for p in outputs if p in existing and existing[p] != outputs[p]]
    same = [p for p in outputs if p in existing and p not in stale]
    new = [p for p in outputs if p not in existing]
    if stale and not force:
        print(
            f"warning: {_names(stale)} {'is' if len(stale) == 1 else 'are'} out of date (runs finished or changed "
            "since, or the file was edited); nothing was written: pass --force to replace, or --out <another folder>",
            file=sys.stderr,
        )
        return
    for p in new:
        _write(p, outputs[p], replace=False)
    for p in stale:
        _write(p, outputs[p], replace=True)
    if new:
        print(f"wrote {_names(new)}")
    if stale:
        print(f"replaced {_names(stale)}")
    if same:
        print(f"{_names(same)}: up to date (the same as this table), not written again")


def _report_runs(unfinished: list, left_out: list, runs: list, include_unfinished: bool) -> None:
    """One line on stderr per run directory a table does not simply count, and the runs' notes."""
    for u in unfinished:
        print(f"not finished: {u.path}: {u.reason}", file=sys.stderr)
    for r in left_out:
        print(f"not counted: {r.path} ({r.incomplete})", file=sys.stderr)
    if left_out:
        print("note: runs not counted are left out of the means; --include-unfinished counts them", file=sys.stderr)
    for r in runs:
        if include_unfinished and r.incomplete:
            print(f"counted although unfinished: {r.path} ({r.incomplete})", file=sys.stderr)
        for note in r.notes:
            print(f"note: {r.path}: {note}", file=sys.stderr)


def sweep_main(
    args: argparse.Namespace, runs: list, unfinished: list, out: Path, layouts: dict, left_out: list | None = None
) -> int:
    """The table of a sweep that is none of the paper's: one row per setting (``runs``: those counted)."""
    from image2sphere.reporting.tables import MISSING_MD

    md, tex = out / f"{SWEEP_NAME}.md", out / f"{SWEEP_NAME}.tex"
    if args.dataset is not None:
        print("warning: --dataset applies to the paper's tables (--table); the sweep table shows every run",
              file=sys.stderr)  # fmt: skip
    table = build_sweep_table(runs, sources=args.run_dirs)
    markdown = sweep_to_markdown(table, unfinished, left_out)
    print(markdown)
    settle_files({md: markdown.encode("utf-8"), tex: sweep_to_latex(table).encode("utf-8")}, args.force)
    print(
        "note: no run was launched with table=<name>, so this is the sweep's own table; --table NAME fills one of "
        f"the paper's layouts instead ({', '.join(sorted(layouts))})",
        file=sys.stderr,
    )
    if args.wandb_project is not None:
        header, lines = sweep_header(table), sweep_lines(table, MISSING_MD, "±")
        _push_to_wandb(args, SWEEP_NAME, table.used, header, lines, markdown, None, out, "sweep-table")
    return 0


def main(argv: list[str] | None = None) -> int:
    layouts = load_layouts()
    args = parse_args(argv, layouts)
    try:
        runs, unfinished = find_runs(args.run_dirs)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    counted, left_out = counted_runs(runs, args.include_unfinished)
    _report_runs(unfinished, left_out, runs, args.include_unfinished)
    # what kind of table: decided by every run with metrics, counted or not, so that it does not change as runs finish
    names = args.table or sorted({str(r.choices.get("table")) for r in runs if r.choices.get("table") in layouts})
    out = args.out if args.out is not None else Path(args.run_dirs[0]) / "tables"
    if not names and is_sweep(runs):
        return sweep_main(args, counted, unfinished, out, layouts, left_out)
    if not names:
        where, choices = ", ".join(args.run_dirs), ", ".join(sorted(layouts))
        found = (
            f"no finished run under {where}" if not runs
            else f"the one finished run under {where} was not launched with table=<name> and is no job of a sweep"
        )  # fmt: skip
        print(
            f"error: {found}; name a paper table with --table ({choices}), or give the directory of a sweep "
            "(python -m src.train -m ...) for a table of its runs",
            file=sys.stderr,
        )
        return 2
    outputs: dict[Path, bytes] = {}
    pushes = []
    with tempfile.TemporaryDirectory() as drawn:  # figures drawn here first, to compare with those written
        for name in names:
            filled = build_table(name, layouts[name], counted, dataset=args.dataset)
            markdown = to_markdown(filled, unfinished, left_out)
            print(markdown)
            outputs[out / f"{name}.md"] = markdown.encode("utf-8")
            outputs[out / f"{name}.tex"] = to_latex(filled).encode("utf-8")
            figure = draw_figure(filled, Path(drawn) / f"{name}.png")
            if figure is not None:
                outputs[out / f"{name}.png"] = figure.read_bytes()
            if not filled.used:
                warning = f"warning: no finished run matches {name}'s rows (see 'not in this table' above)"
                print(warning, file=sys.stderr)
            pushes.append((filled, markdown, figure))
        settle_files(outputs, args.force)
        if args.wandb_project is not None:  # this table's figure, whether or not its file was written
            for filled, markdown, figure in pushes:
                _push_paper_table(args, filled, markdown, figure, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
