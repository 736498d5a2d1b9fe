"""Report layer: stored runs -> figures and tables, with lineage. Never simulates.

A `Run` is a stored run directory; tables are read from parquet and checked against the hashes
in run.json. Figures are saved as PNG and PDF (deterministic bytes) with a JSON beside them that
names the runs, the hashes of the tables drawn from, the script and the code version.
"""
from __future__ import annotations

import functools
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from ..errors import DamagedRecord, LineageError, warnings_as_lines  # noqa: E402
from ..experiment.store import Run, RunStore, files, layout, provenance  # noqa: E402
from ..experiment.store.run import warn  # noqa: E402
from ..numerics.analysis import rms_band  # noqa: E402

COLUMN_WIDTH, PAGE_WIDTH = 3.5, 7.16        # IEEE column and page widths, inches
STYLE = {"font.size": 8, "axes.titlesize": 8, "axes.labelsize": 8, "legend.fontsize": 7, "xtick.labelsize": 7,
         "ytick.labelsize": 7, "lines.linewidth": 1.0, "figure.dpi": 100, "savefig.dpi": 300,
         "axes.prop_cycle": matplotlib.cycler(color=["black", "0.45", "0.7"], linestyle=["-", "--", ":"]),
         "pdf.fonttype": 42}


matplotlib.rcParams.update(STYLE)


def script(main) -> None:
    """Run a report script's main: a LineageError ends it with one line on stderr and exit code 1."""
    import sys
    try:
        with warnings_as_lines():
            main()
    except (LineageError, DamagedRecord) as err:
        sys.exit(f"{Path(sys.argv[0]).name}: {err}")


# keys a run of a shipped sweep may also override and still be the paper's: the sizes of its Monte Carlo
# and horizons (what a small or a long version of the same experiment changes), seeds and tracking
SIZES = ("seed", "store", "reuse", "enkf.ensemble_size", "closed_loop.paths", "closed_loop.horizon",
         "closed_loop.rate_window", "closed_loop.disturbance.until", "closed_loop.floor_paths",
         "closed_loop.chunk_paths", "closed_loop.workers", "identification.horizon", "identification.K0",
         "identification.K1", "tracking")


@functools.cache
def swept_keys(sweep: str) -> frozenset[str] | None:
    """The keys the shipped sweep config rdsexp.conf/sweep/NAME.yaml varies; None if none is shipped.
    Read once per process (a report asks it for every run)."""
    from importlib.resources import files as package_files
    path = package_files("rdsexp.conf") / "sweep" / f"{sweep}.yaml"
    if not path.is_file():
        return None
    return frozenset(OmegaConf.select(OmegaConf.create(path.read_text()), "hydra.sweeper.params") or {})


def of_shipped_sweep(run: Run, sweep: str) -> bool:
    """Whether a run of sweep NAME is the shipped sweep's experiment on the paper's plant: its plant and
    model are the paper's, and its command line overrides only the keys the sweep varies and SIZES. A
    user's `+sweep=NAME plant=mine`, or one that changes what a figure shows (another gain method, Q,
    disturbance), is not."""
    keys = swept_keys(sweep)
    record = run.record
    if keys is None:
        return True
    if record.summary.plant != "paper" or record.summary.model != "paper":
        return False
    for override in record.overrides:
        key = override.split("=", 1)[0].lstrip("+~")
        if key != "sweep" and key not in keys and not any(key == k or key.startswith(f"{k}.") for k in SIZES):
            return False
    return True


def sweep_of(run: Run) -> str | None:
    """The name a run's sweep was launched with (`+sweep=NAME`, as run.json records it), None for a run that is
    no sweep's job or a sweep launched without a name."""
    sweep = run.record.sweep
    return sweep.recorded_name if sweep is not None else None


def load_runs(root: Path, sweep: str | None = None) -> list[Run]:
    """Complete runs under root (optionally of one sweep name, and then only the runs of the shipped
    sweep's experiment, `of_shipped_sweep`), the latest sweep of that name only. A damaged run
    (run.json or a table unreadable, missing or modified) is named in one warning line and left out."""
    runs = sorted(RunStore(root).runs(), key=lambda run: str(run.dir))
    runs = [r for r in runs if r.record.complete and r.record.tables]
    if sweep is not None:
        runs = [r for r in runs if sweep_of(r) == sweep and of_shipped_sweep(r, sweep)]
    intact = []                     # the files of the selected runs only (each file hashed once per process)
    for r in runs:
        problems = r.damage()
        if problems:
            warn(DamagedRecord(r.dir, "; ".join(problems)))
        else:
            intact.append(r)
    runs = intact
    if sweep is not None and runs:
        latest = max(str(r.record.sweep.dir) for r in runs)
        runs = [r for r in runs if str(r.record.sweep.dir) == latest]
    return runs


def check_versions(runs: list[Run], allow_mixed: bool = False) -> str:
    """The one code version of `runs`; LineageError if they differ (unless allowed)."""
    versions = sorted({r.code for r in runs})
    if len(versions) > 1 and not allow_mixed:
        raise LineageError(f"runs from {len(versions)} code versions {versions}: re-run them or pass --allow-mixed")
    return versions[0] if len(versions) == 1 else "mixed:" + ",".join(versions)


def check_pooling(runs: list[Run], keys=()) -> None:
    """LineageError (one line) when runs that a figure or table pools as seeds of one experiment are not:
    runs of one plant name whose plant contents (plant_hash) differ, or whose path counts
    (closed_loop.paths) differ, unless `keys` (what the figure varies) include closed_loop.paths."""
    by_plant: dict[str, list[Run]] = {}
    for r in runs:
        by_plant.setdefault(str(r.record.summary.plant), []).append(r)
    for plant, members in by_plant.items():
        hashes = sorted({(r.record.plant_hash or "")[:12] for r in members} - {""})
        if len(hashes) > 1:
            raise LineageError(f"runs of plant {plant} with {len(hashes)} different contents (plant_hash "
                               f"{', '.join(hashes)}) would be pooled: keep one plant file per name in the store")
        paths = sorted({r.get("closed_loop.paths") for r in members}, key=str)
        if len(paths) > 1 and "closed_loop.paths" not in keys:
            raise LineageError(f"runs of plant {plant} with different path counts (closed_loop.paths "
                               f"{', '.join(map(str, paths))}) would be pooled: run the sweep again at one count")


def sweep_runs(root: Path, sweep: str, allow_mixed: bool = False) -> list[Run]:
    """The runs of the latest stored `sweep` under root, of one code version (unless allowed) and one
    plant content and path count per plant (`check_pooling`); LineageError when there are none."""
    runs = load_runs(root, sweep)
    check_versions(runs, allow_mixed)
    if not runs:
        raise LineageError(f"no stored runs of sweep {sweep!r} under {root}")
    check_pooling(runs, swept_keys(sweep) or ())
    return runs


def latest_per_plant(runs: list[Run], sweep: str, keys: tuple[str, ...]) -> dict[str, list[Run]]:
    """plant name -> the runs of every stored `sweep` on that plant, the latest run of each point
    (the config values at `keys`): a study may be run as several sweeps (one per plant or variant),
    and a later sweep replaces the earlier runs of the points it repeats. LineageError where one plant's
    runs differ in content or path count (`check_pooling`)."""
    latest = {}
    for r in sorted((r for r in runs if sweep_of(r) == sweep), key=lambda r: r.record.created or ""):
        latest[(r.get("plant.name"), *(str(r.get(k)) for k in keys))] = r
    out: dict[str, list[Run]] = {}
    for point, r in latest.items():
        out.setdefault(point[0], []).append(r)
    for members in out.values():
        check_pooling(members, keys)
    return out


def select(runs: list[Run], **where) -> list[Run]:
    """Runs whose config matches every `key=value` (dots in keys written as __)."""
    return [r for r in runs if all(r.get(k.replace("__", ".")) == v for k, v in where.items())]


@functools.lru_cache(maxsize=1)
def drawing_code() -> str:
    """The code version of this report process (`provenance.code_version`), once per process."""
    return provenance.code_version()["version"]


def lineage(runs: list[Run], script: str, **extra) -> dict:
    """What an output was drawn from: the runs whose tables it read (ids, table hashes), their code
    version, the script and the code version that drew it (`drawn_by`)."""
    used = [r for r in runs if r.used]
    # an output computed from configs alone (no stored run, e.g. pole_sets) names the code that made it
    version = check_versions(used, allow_mixed=True) if used else drawing_code()
    return {"script": script, "code_version": version, "drawn_by": drawing_code(),
            "runs": [{"id": r.id, "dir": str(r.dir), "tables": dict(sorted(r.used.items()))} for r in used], **extra}


def _stored_lineage(out_dir: Path, name: str) -> dict | None:
    try:
        return files.read_json(Path(out_dir) / f"{name}.json")
    except (OSError, ValueError):
        return None


def _same_source(a: dict, b: dict) -> bool:
    """Two lineage records of the same runs, tables, script and code (whatever their outputs)."""
    return {k: v for k, v in a.items() if k != "outputs"} == {k: v for k, v in b.items() if k != "outputs"}


def up_to_date(out_dir: Path, name: str, record: dict) -> bool:
    """Whether name.json holds this lineage `record` (a figure and a table of one name share it) and
    every output the record names exists: the same runs, table hashes and code made them, so writing
    them again would give the same bytes."""
    stored = _stored_lineage(out_dir, name)
    return stored is not None and _same_source(stored, record) and set(record["outputs"]) <= set(stored["outputs"]) \
        and all((Path(out_dir) / o).exists() for o in record["outputs"])


def write_lineage(out_dir: Path, name: str, record: dict) -> None:
    """name.json: the lineage `record`, its outputs joined with those already recorded there from the
    same source (a figure and a table of one name)."""
    stored = _stored_lineage(out_dir, name)
    if stored is not None and _same_source(stored, record):
        record = record | {"outputs": sorted(set(stored["outputs"]) | set(record["outputs"]))}
    files.write_json(Path(out_dir) / f"{name}.json", record)


def save_figure(fig, out_dir: Path, name: str, runs: list[Run], script: str, caption: str = "") -> list[Path]:
    """PNG + PDF (byte-identical on re-runs), name.caption.md (the numbers, out of the figure) and
    name.json with the lineage; nothing is rewritten when the lineage is unchanged (`up_to_date`)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [out_dir / f"{name}.png", out_dir / f"{name}.pdf"] + ([out_dir / f"{name}.caption.md"] if caption else [])
    record = lineage(runs, script, outputs=[p.name for p in paths])
    if up_to_date(out_dir, name, record):          # rendering is most of a report's second call
        plt.close(fig)
        return paths
    fig.savefig(paths[0], metadata={"Software": None})
    fig.savefig(paths[1], metadata={"CreationDate": None, "ModDate": None, "Producer": None, "Creator": None})
    plt.close(fig)
    if caption:
        files.atomic_write_bytes(paths[-1], (caption.strip() + "\n").encode())
    write_lineage(out_dir, name, record)
    return paths


def log_ticks(ax) -> None:
    """Readable log y-axis: a labelled tick per decade (at most ~6 labels), unlabelled minor ticks."""
    from matplotlib.ticker import LogFormatterMathtext, LogLocator, NullFormatter
    ax.yaxis.set_major_locator(LogLocator(base=10, numticks=7))
    ax.yaxis.set_major_formatter(LogFormatterMathtext())
    ax.yaxis.set_minor_locator(LogLocator(base=10, subs=np.arange(2, 10), numticks=12))
    ax.yaxis.set_minor_formatter(NullFormatter())


def interval(mean: float, low: float, high: float, digits: int = 4) -> str:
    """'mean [low, high]' (low/high omitted when NaN)."""
    if not np.isfinite(low):
        return f"{mean:.{digits}f}"
    return f"{mean:.{digits}f} [{low:.{digits}f}, {high:.{digits}f}]"


def squared_norms(run: Run, experiment: str, ks) -> np.ndarray:
    """||q_k||^2 per path at the steps ks of one stored loop: (len(ks), P)."""
    q = trajectory_array(run.table("trajectories"), experiment, "q")
    return np.sum(q[list(ks)] ** 2, axis=-1)


def figure(width: float, height: float, nrows: int = 1, ncols: int = 1, **kw):
    """A figure in the report's style (IEEE sizes in inches, grayscale-readable)."""
    return plt.subplots(nrows, ncols, figsize=(width, height), layout="constrained", **kw)


def rms_with_band(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """sqrt(E||q_k||^2) over paths with its 95% band: q (K+1, P, n) -> 3 x (K+1,) (`analysis.rms_band`,
    the band the recording shows too)."""
    return rms_band(np.sum(q ** 2, axis=-1))


def trajectory_array(table: pd.DataFrame, experiment: str, quantity: str) -> np.ndarray:
    """(K+1, P, dim) array of QUANTITY[i] columns of one experiment of a trajectories table."""
    rows = table[table["experiment"] == experiment].sort_values(["k", "path"], kind="stable")
    cols = sorted((c for c in table.columns if c.startswith(quantity + "[")),
                  key=lambda c: int(c[len(quantity) + 1:-1]))
    steps, paths = rows["k"].nunique(), rows["path"].nunique()
    return rows[cols].to_numpy().reshape(steps, paths, len(cols))


def seed_interval(values, level: float = 0.95) -> tuple[float, float, float, int]:
    """Mean and t-interval of the mean over seeds (NaN-free values), and the count."""
    from scipy import stats
    v = np.asarray([x for x in values if np.isfinite(x)], dtype=float)
    if v.size == 0:
        return np.nan, np.nan, np.nan, 0
    if v.size == 1:
        return float(v[0]), np.nan, np.nan, 1
    half = stats.t.ppf(0.5 + level / 2, v.size - 1) * v.std(ddof=1) / np.sqrt(v.size)
    return float(v.mean()), float(v.mean() - half), float(v.mean() + half), int(v.size)


def write_table(frame: pd.DataFrame, out_dir: Path, name: str, runs: list[Run], script: str, **extra) -> None:
    """A report table as CSV and markdown, with its lineage JSON (plus `extra` entries)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    files.atomic_write_bytes(out_dir / f"{name}.csv", frame.to_csv(index=False).encode())
    files.atomic_write_bytes(out_dir / f"{name}.md", _markdown(frame).encode())
    write_lineage(out_dir, name, lineage(runs, script, outputs=[f"{name}.csv", f"{name}.md"], **extra))


def write_caption(out_dir: Path, name: str, text: str) -> Path:
    """name.caption.md beside a table or figure: the sentence that says what it shows."""
    out_dir.mkdir(parents=True, exist_ok=True)
    files.atomic_write_bytes(out_dir / f"{name}.caption.md", (text.strip() + "\n").encode())
    return out_dir / f"{name}.caption.md"


def _markdown(frame: pd.DataFrame) -> str:
    def cell(v) -> str:
        if v is None or (isinstance(v, float) and np.isnan(v)):
            return ""
        return f"{v:.6g}" if isinstance(v, float) else str(v)
    lines = ["| " + " | ".join(frame.columns) + " |", "|" + "---|" * len(frame.columns)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in frame.itertuples(index=False)]
    return "\n".join(lines) + "\n"


REFERENCE = Path(__file__).resolve().parents[1] / "paper" / "reference.yaml"
PAPER_SWEEP = "paper"


def reference() -> dict:
    """The paper's reported numbers (rdsexp/paper/reference.yaml)."""
    return OmegaConf.to_container(OmegaConf.load(REFERENCE))


def parser(description: str):
    """The argument parser of the report scripts with the common options --root, --out, --allow-mixed."""
    import argparse
    parser = argparse.ArgumentParser(description=description)
    root = Path(layout.DEFAULT_ROOT)
    parser.add_argument("--root", type=Path, default=root, help=f"where the runs are (default {root}/)")
    parser.add_argument("--out", type=Path, default=root / "report", help=f"where to write ({root}/report/)")
    parser.add_argument("--allow-mixed", action="store_true", help="allow runs made by different code versions")
    return parser


def arguments(description: str, argv=None):
    """The common options of the report scripts, parsed (see `parser`)."""
    return parser(description).parse_args(argv)


def paper_runs(args) -> list[Run]:
    """The latest stored `paper` sweep under args.root, refused if of mixed code versions."""
    runs = load_runs(args.root, PAPER_SWEEP)
    check_versions(runs, args.allow_mixed)
    return runs


def first_seed(runs: list[Run], method: str = "proposed") -> Run:
    """The run of `method` with the smallest seed: the stand-in for the paper's single run."""
    chosen = sorted(select(runs, gain__method=method), key=lambda r: r.get("seed"))
    if not chosen:
        raise LineageError(f"no stored run with gain.method = {method}")
    return chosen[0]
