"""``python -m src.tables RUN_DIR [RUN_DIR ...]``: the paper's tables, or a table of any sweep, from finished runs.

Reads every run directory at or below the given directories (each run's ``metrics.json`` and
``.hydra/``). Runs launched for one of the paper's tables (``table=tableN``; or the tables named with
``--table``) fill that table's layout beside the paper's published numbers, as Markdown (printed, and
``<out>/<table>.md``), LaTeX (``<out>/<table>.tex``) and, for the tables that have one, a figure
(``<out>/<table>.png``). Any other sweep (``python -m src.train -m ...``, an Optuna study) gives one
table with a row per setting, the overrides that differ between its runs as columns and the headline
metrics over seeds (``<out>/sweep.md``, ``<out>/sweep.tex``; :mod:`image2sphere.reporting.sweep_table`).
See ``--help``.
"""

import argparse
import sys
from pathlib import Path

import image2sphere  # noqa: F401  (the torchvision guard, before anything imports torchvision)
from image2sphere.reporting import (
    build_sweep_table,
    build_table,
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

Run directories without metrics.json are listed as not finished. Existing output files are never
replaced unless --force is given.
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
    parser.add_argument("--force", action="store_true", help="replace output files that already exist")
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


def _refuse_existing(targets: list[Path], force: bool) -> bool:
    """Whether to stop: some of ``targets`` exist and ``--force`` was not given (the error is printed)."""
    existing = [str(t) for t in targets if t.exists()]
    if existing and not force:
        print(
            f"error: {', '.join(existing)} already exist(s); pass --force to replace, or --out <another folder>",
            file=sys.stderr,
        )
        return True
    return False


def sweep_main(args: argparse.Namespace, runs: list, unfinished: list, out: Path, layouts: dict) -> int:
    """The table of a sweep that is none of the paper's: one row per setting."""
    from image2sphere.reporting.tables import MISSING_MD

    md, tex = out / f"{SWEEP_NAME}.md", out / f"{SWEEP_NAME}.tex"
    if _refuse_existing([md, tex], args.force):
        return 2
    if args.dataset is not None:
        print("warning: --dataset applies to the paper's tables (--table); the sweep table shows every run",
              file=sys.stderr)  # fmt: skip
    table = build_sweep_table(runs, sources=args.run_dirs)
    markdown = sweep_to_markdown(table, unfinished)
    print(markdown)
    out.mkdir(parents=True, exist_ok=True)
    md.write_text(markdown, encoding="utf-8")
    tex.write_text(sweep_to_latex(table), encoding="utf-8")
    print(f"wrote {md}, {tex}")
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
    for u in unfinished:
        print(f"not finished: {u.path}: {u.reason}", file=sys.stderr)
    for r in runs:
        for note in r.notes:
            print(f"note: {r.path}: {note}", file=sys.stderr)
    names = args.table or sorted({str(r.choices.get("table")) for r in runs if r.choices.get("table") in layouts})
    out = args.out if args.out is not None else Path(args.run_dirs[0]) / "tables"
    if not names and is_sweep(runs):
        return sweep_main(args, runs, unfinished, out, layouts)
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
    targets = [out / f"{n}.{ext}" for n in names for ext in ("md", "tex", "png")]
    if _refuse_existing(targets, args.force):
        return 2
    out.mkdir(parents=True, exist_ok=True)
    for name in names:
        filled = build_table(name, layouts[name], runs, dataset=args.dataset)
        markdown = to_markdown(filled, unfinished)
        print(markdown)
        (out / f"{name}.md").write_text(markdown, encoding="utf-8")
        (out / f"{name}.tex").write_text(to_latex(filled), encoding="utf-8")
        figure = draw_figure(filled, out / f"{name}.png")
        written = [out / f"{name}.md", out / f"{name}.tex"] + ([figure] if figure else [])
        print("wrote " + ", ".join(str(w) for w in written))
        if not filled.used:
            print(f"warning: no finished run matches {name}'s rows (see 'not in this table' above)", file=sys.stderr)
        if args.wandb_project is not None:
            _push_paper_table(args, filled, markdown, figure, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
