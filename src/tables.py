"""``python -m src.tables RUN_DIR [RUN_DIR ...]``: the paper's tables from finished runs.

Reads every run directory at or below the given directories (each run's ``metrics.json`` and
``.hydra/``), fills the layout of each table those runs were launched for (``table=tableN``; or the
tables named with ``--table``) and writes it beside the paper's published numbers, as Markdown
(printed, and ``<out>/<table>.md``), LaTeX (``<out>/<table>.tex``) and, for the tables that have
one, a figure (``<out>/<table>.png``). See ``--help``.
"""

import argparse
import sys
from pathlib import Path

import image2sphere  # noqa: F401  (the torchvision guard, before anything imports torchvision)
from image2sphere.reporting import build_table, draw_figure, find_runs, load_layouts, to_latex, to_markdown

EPILOG = """\
examples:
  python -m src.train table=table7 encoder.weights=IMAGENET1K_V2        # the runs of Table 7
  python -m src.tables logs/table7/multiruns/<date>_<time>_<pid>        # Table 7 next to the paper's
  python -m src.tables logs/table1/multiruns/<sweep> --table table5     # Table 5 from Table 1's runs
  python -m src.tables logs/table7/multiruns/<a> logs/table7/multiruns/<b>   # pool two sweeps (seeds)
  python -m src.tables <small sweep on the built-in data> --dataset symsol_rendered

Each cell is the mean over the matching finished runs (seeds), +- their sample standard deviation;
under it the paper's number and the difference (ours - paper). A cell without a run is shown as a
missing cell, never as 0; "n/a" is a metric the method does not have (a point estimate's log
likelihood). Run directories without metrics.json are listed as not finished. Existing output files
are never replaced unless --force is given.
"""


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    layouts = load_layouts()
    parser = argparse.ArgumentParser(
        prog="python -m src.tables",
        description="Print and write the I2S paper's tables from finished runs, beside the published numbers.",
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
        help=f"table(s) to write ({', '.join(sorted(layouts))}); default: the table=... the runs were launched with",
    )  # fmt: skip
    parser.add_argument(
        "--dataset", default=None,
        help="match runs on this dataset instead of the paper's (e.g. symsol_rendered for a small run on the built-in "
        "data); the published numbers are then not comparable, and the table says so",
    )  # fmt: skip
    parser.add_argument(
        "--out", type=Path, default=None, help="folder for <table>.md/.tex/.png (default: <first RUN_DIR>/tables)"
    )
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


def _push_to_wandb(args: argparse.Namespace, filled, markdown: str, figure: Path | None, out: Path) -> None:
    import wandb

    project, entity = args.wandb_project, args.wandb_entity
    if not project:  # the sweep's own project: where its runs logged
        projects = {r.get("logger.wandb.project", None) for r in filled.used} - {None}
        project = sorted(projects)[0] if len(projects) == 1 else "image2sphere"
        entities = {r.get("logger.wandb.entity", None) for r in filled.used} - {None}
        entity = entity or (sorted(entities)[0] if len(entities) == 1 else None)

    columns = ["method", "source"] + [
        c["title"] if not c.get("group") else f"{c['group']}: {c['title']}" for c in filled.layout["columns"]
    ]
    from image2sphere.reporting.tables import MISSING_MD, table_lines

    data = [[label, source, *cells] for label, source, cells in table_lines(filled, MISSING_MD, "±")]
    run = wandb.init(
        project=project, entity=entity, mode=args.wandb_mode, dir=str(out),
        job_type="paper-table", name=filled.name,
        config={"table": filled.name, "runs": [str(r.path) for r in filled.used]},
    )  # fmt: skip
    log = {
        filled.name: wandb.Table(columns=columns, data=data),
        f"{filled.name}_markdown": wandb.Html(f"<pre>{markdown}</pre>"),
    }
    if figure is not None:
        log[f"{filled.name}_figure"] = wandb.Image(str(figure))
    run.log(log)
    run.finish()


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    layouts = load_layouts()
    try:
        runs, unfinished = find_runs(args.run_dirs)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    for u in unfinished:
        print(f"not finished: {u.path}: {u.reason}", file=sys.stderr)
    names = args.table or sorted({str(r.choices.get("table")) for r in runs if r.choices.get("table") in layouts})
    if not names:
        print(
            f"error: none of the {len(runs)} finished runs under {', '.join(args.run_dirs)} was launched with "
            f"table=<name>; name the table with --table ({', '.join(sorted(layouts))})",
            file=sys.stderr,
        )
        return 2
    out = args.out if args.out is not None else Path(args.run_dirs[0]) / "tables"
    targets = [out / f"{n}.{ext}" for n in names for ext in ("md", "tex", "png")]
    existing = [str(t) for t in targets if t.exists()]
    if existing and not args.force:
        print(
            f"error: {', '.join(existing)} already exist(s); pass --force to replace, or --out <another folder>",
            file=sys.stderr,
        )
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
            _push_to_wandb(args, filled, markdown, figure, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
