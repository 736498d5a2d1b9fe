"""The run catalog as a public module: `rdsexp-runs ...` or `python -m rdsexp.runs ...` (see
rdsexp.experiment.catalog), and `plot`, a figure of any sweep (rdsexp.report.sweep_plot), which sits a
layer above the store and is added here.

    rdsexp-runs plot SWEEP|--where "..." --x KEY [--x KEY2] --y METRIC [--hue KEY] [--logx] [--logy] [--out DIR]
    rdsexp-runs plot RUN [--out DIR]   (the run's figure: each loop's RMS against its exact curve, the law of xi)
    rdsexp-runs export --mlflow URI [SWEEP|RUN] [--where "..."] [--experiment NAME] [--no-tables] [--root DIR]
    rdsexp-runs export --data RUN --out FILE [--root DIR]   (a run's identification u, y in the data format)
"""
import os
import sys
from pathlib import Path

from .experiment.catalog import *  # noqa: F403
from .experiment.catalog import DEFAULT_ROOT, locate_sweep, open_run, search
from .experiment.catalog import __all__ as _catalog
from .experiment.catalog import main as _main

__all__ = [*_catalog, "cli", "plot", "plot_run"]


def plot(sweep: str | None = None, *, x, y: str, where: str | None = None, hue: str | None = None,
         logx: bool = False, logy: bool = False, out=None, name: str | None = None, root=DEFAULT_ROOT):
    """Draw metric `y` against the swept key `x` (two keys: a heatmap) for the runs of `sweep` (a sweep
    directory or name, `rdsexp-runs show`) and/or those matching `where` (`search`), one row per
    computation. Returns (the points table, the files written: PNG, PDF, caption, CSV, lineage JSON);
    out: the directory (default the sweep's directory, else outputs/report)."""
    from .report import sweep_plot
    if sweep is None and where is None:
        raise ValueError("plot: name a SWEEP or give --where")
    directory = None
    if sweep is not None:
        directory = locate_sweep(sweep, Path(root))
        if directory is None:
            raise LookupError(f"no sweep {sweep!r} under {root}")
    table = search(directory if directory is not None else Path(root), where)
    if not len(table):
        raise ValueError(f"plot: no runs{f' of sweep {sweep}' if sweep else ''}{f' with {where}' if where else ''}")
    out = Path(out) if out is not None else (directory if directory is not None else Path(root) / "report")
    keys = x if isinstance(x, str) else list(x)
    points = sweep_plot.aggregate(table, keys, y, hue=hue)
    return points, sweep_plot.plot(table, keys, y, hue=hue, logx=logx, logy=logy, out=out, name=name)


def plot_run(run, out=None, root=DEFAULT_ROOT) -> Path:
    """Draw a stored run's figure (`rdsexp.experiment.figure`: each loop's RMS against its exact curve, the
    modeled law of xi) from its tables into `out` (a directory; default the run's own). Returns the file. A run
    recorded with its figure (tracking.figure) keeps it: without `out`, that file is returned, not redrawn."""
    from .experiment.figure import draw, squares_of
    from .experiment.store import layout
    stored = open_run(run, root)
    out = Path(out) if out is not None else stored.dir
    target = out / layout.FIGURE
    if out == stored.dir and target.exists():         # what the run recorded is never overwritten
        return target
    out.mkdir(parents=True, exist_ok=True)
    return draw(target, squares_of(stored.table("trajectories")), stored.table("metrics"), stored.table("exact"),
                stored.record.summary)


def _add_plot_arguments(p) -> None:
    p.add_argument("sweep", nargs="?", help="a sweep directory or name, or a run (its figure: no --x or --y) "
                                            "(default: the runs --where selects)")
    p.add_argument("--where", help='filter, e.g. "plant == \'mine\' and enkf.q_scale >= 1"')
    p.add_argument("--x", action="append", help="the swept key (twice, or KEY1,KEY2: a heatmap)")
    p.add_argument("--y", help="the metric, e.g. closed_loop_rate")
    p.add_argument("--hue", help="a key drawn as one line per value")
    p.add_argument("--logx", action="store_true")
    p.add_argument("--logy", action="store_true")
    p.add_argument("--out", help="directory of the figure (default: the sweep's directory, else ROOT/report)")
    p.add_argument("--name", help="file name without extension (default: Y_vs_X)")
    p.add_argument("--root", default=str(DEFAULT_ROOT))


def _plot_command(args) -> int:
    if args.x is None and args.y is None and args.sweep is not None and args.where is None:
        print(plot_run(args.sweep, out=args.out, root=args.root))          # a run's own figure
        return 0
    if args.x is None or args.y is None:
        raise ValueError("plot: a sweep's figure needs --x and --y (a run's figure takes neither)")
    keys = [k.strip() for part in args.x for k in part.split(",") if k.strip()]
    points, paths = plot(args.sweep, x=keys[0] if len(keys) == 1 else keys, y=args.y, where=args.where,
                         hue=args.hue, logx=args.logx, logy=args.logy, out=args.out, name=args.name,
                         root=args.root)
    print(points.to_string(index=False, float_format=lambda v: f"{v:.4g}", na_rep="-"))
    print("\n".join(str(p) for p in paths))
    return 0


def _add_export_arguments(p) -> None:
    p.add_argument("sweep", nargs="?", help="a sweep (directory or name) or a run (directory or id); default: "
                                            "the runs --where selects")
    p.add_argument("--mlflow", metavar="URI", help="MLflow tracking URI, e.g. http://127.0.0.1:5000")
    p.add_argument("--data", metavar="RUN", help="a run's identification inputs and outputs in the data format "
                                                 "(path, k, u[i], y[i]) for `rdsexp data=FILE model=NAME`")
    p.add_argument("--out", metavar="FILE", help="with --data: the file to write (.csv, .csv.gz, .parquet)")
    p.add_argument("--where", help='filter, e.g. "plant == \'mine\' and enkf.q_scale >= 1"')
    p.add_argument("--experiment", default="rdsexp", help="MLflow experiment (default: rdsexp; created if missing)")
    p.add_argument("--no-tables", action="store_true", help="artifacts: run.json and config.yaml, not the tables")
    p.add_argument("--root", default=str(DEFAULT_ROOT))


def _export_command(args) -> int:
    if args.data is not None:
        if args.out is None or args.mlflow is not None:
            print("rdsexp-runs export: --data RUN needs --out FILE (and no --mlflow)", file=sys.stderr)
            return 2
        from .experiment.catalog import export_data
        rows, note = export_data(args.data, args.out, root=args.root)
        print(f"{args.out}: {rows} rows ({note})")
        return 0
    if args.mlflow is None:
        print("rdsexp-runs export: give --mlflow URI or --data RUN --out FILE", file=sys.stderr)
        return 2
    from .report import to_mlflow
    report = to_mlflow.export(args.sweep, args.mlflow, args.experiment, where=args.where, root=args.root,
                              tables=not args.no_tables)
    print("\n".join(report.lines()))
    return 0


COMMANDS = {"plot": ("a metric against swept keys: mean over seeds, 95%% interval, failed fraction; PNG, PDF, "
                     "lineage; or a run's figure", _add_plot_arguments, _plot_command),
            "export": ("stored runs to an MLflow tracking server (a sweep: a parent run and its jobs; once each)",
                       _add_export_arguments, _export_command)}


def main(argv=None) -> int:
    return _main(argv, COMMANDS)


def cli() -> None:
    """Console entry point `rdsexp-runs`."""
    try:
        code = main()
    except BrokenPipeError:            # `rdsexp-runs list | head`: the reader stopped early, not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        code = 0
    sys.exit(code)


if __name__ == "__main__":
    cli()
