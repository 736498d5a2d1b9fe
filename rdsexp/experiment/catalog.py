"""Run catalog: `rdsexp-runs list [DIR] | show RUN|SWEEP | diff A B | view RUN|SWEEP | verify RUN |
check [DIR]`, and the Python API `search` / `load` (`rdsexp.runs.search(...)`, like MLflow's search_runs).

A run is a directory with a run.json (`rdsexp.experiment.store`, which owns the layout); RUN is
its path or its id (a directory name under outputs/, or SWEEP/JOB for a sweep job); a SWEEP is a
sweep directory or its name under outputs/sweeps/. Damaged records are skipped with one warning
line each, or reported as damaged. This module is the command line over the store: the table of
runs, its queries, diff, verify and check.
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import DamagedRecord, warnings_as_lines
from . import metrics, schema
from .store import Run, RunRecord, RunStore, layout, provenance
from .store.table import MISSING, as_text, changed_params, one_row_per_run, sweep_results

DEFAULT_ROOT = Path(layout.DEFAULT_ROOT)
__all__ = ["DEFAULT_ROOT", "changed", "check", "compare_tables", "diff", "load", "main", "open_run", "record", "search",
           "verify"]
# `list`'s default columns: the run's identity, then the metrics the registry lists (`metrics.listed`)
IDENTITY_SHOWN = ["id", "sweep", "plant", "plant_hash", "seed", "overrides", "status"]


def search(root=DEFAULT_ROOT, where: str | None = None, copies: bool = False) -> pd.DataFrame:
    """One row per run under root (oldest first), like MLflow's search_runs: the run's identity (id,
    sweep (`+sweep=NAME`, or the overrides of a `-m` run), sweep_id (its directory), resumes (the
    interrupted sweep it resumes), job, seed, status,
    plant (its `name:`, else its file name), model, method, overrides, reused_from, created, code
    (version), config_hash, dir), `metrics.<name>` (key numbers of run.json's summary) and
    `params.<dotted.key>` (every resolved scalar config value); see `rdsexp.experiment.store.table`.

    where: a filter over these columns, e.g. ``"params.enkf.q_scale >= 1 and metrics.lam < 0.9"``
    (pandas query syntax; `=` also compares; a name without its params./metrics. prefix is found).
    A sweep job that reused a stored run is a copy of it: among the rows that match, each computation
    is one row (the original where it matches; `store.table.one_row_per_run`), so that a mean over
    seeds counts it once. copies: every matching record, copies included."""
    table = RunStore(root).table(params=True)
    table = query(table, where) if where else table
    return table if copies else one_row_per_run(table)


def column(table: pd.DataFrame, name: str) -> str:
    """The column `name` names: itself, params.NAME, metrics.NAME or the one column ending in .NAME."""
    for candidate in (name, f"params.{name}", f"metrics.{name}"):
        if candidate in table.columns:
            return candidate
    ends = [c for c in table.columns if c.endswith(f".{name}")]
    if len(ends) == 1:
        return ends[0]
    raise ValueError(f"{name!r} names {'no' if not ends else 'more than one'} column"
                     + (f" ({', '.join(ends)})" if ends else ""))


def query(table: pd.DataFrame, where: str) -> pd.DataFrame:
    """Rows of a `search` table that satisfy `where` (see `search`); ValueError naming a bad column."""
    parts = re.split(r"""("[^"]*"|'[^']*')""", where)      # leave quoted strings alone
    for i in range(0, len(parts), 2):
        text = re.sub(r"(?<![=!<>])=(?![=])", "==", parts[i])
        parts[i] = re.sub(r"(?<![\w.`])([A-Za-z_]\w*(?:\.\w+|\[\d+\])*)",
                          lambda m: _name(table, m.group(1)), text)
    try:
        return table.query("".join(parts), engine="python").reset_index(drop=True)
    except (pd.errors.UndefinedVariableError, SyntaxError, TypeError, KeyError) as err:
        raise ValueError(f"where {where!r}: {err}") from None


def _name(table: pd.DataFrame, token: str) -> str:
    if token in ("and", "or", "not", "in", "True", "False", "None", "nan"):
        return token
    try:
        return f"`{column(table, token)}`"
    except ValueError:
        return token if "." not in token else f"`{token}`"


changed = changed_params      # the params columns whose value is not the same in every row


def load(run, table: str, long: bool = False, root=DEFAULT_ROOT) -> pd.DataFrame:
    """A stored table of one run with the run's id as a first column `run`.

    run: a run directory, an id, or a row of `search`. table: trajectories, identification, paths,
    model, gains, metrics, exact or members. long: trajectories, identification and members in
    long form, one row per (experiment, path, [member,] k, quantity, index) with its `value`
    (quantity "x_filt_mean", index i of the column "x_filt_mean[i]"; the gain in use "F[i,j]": quantity
    "F<i>", index j)."""
    stored = open_run(run, root)
    tables = stored.record.tables
    if table not in tables:
        raise ValueError(f"table {table!r}: run {stored.id} has {', '.join(tables) or 'no tables'}")
    frame = stored.table(table, described=True)      # checked against run.json's hash
    frame.insert(0, "run", stored.id)
    if not long:
        return frame
    if table not in ("trajectories", "identification", "members"):
        raise ValueError(f"long=True: {table!r} is not a trajectory table (trajectories, identification, members)")
    keys = [c for c in frame.columns if "[" not in c]
    out = frame.melt(id_vars=keys, var_name="column", value_name="value")
    parts = out["column"].str.extract(schema.VALUE_COLUMN.pattern)
    quantity = parts["quantity"] + parts["row"].fillna("")          # F[i,j]: quantity F<i>, index j
    out = out.drop(columns="column").assign(quantity=quantity, index=parts["index"].astype(np.int64))
    order = [c for c in ("run", "experiment", "path", "member", "k") if c in keys]
    return out[[*order, "quantity", "index", "value"]]       # column by column, as melted


def open_run(run, root=DEFAULT_ROOT) -> Run:
    """The stored run `run` (a run directory, an id, or a row of `search`): its typed record (`.record`:
    identity, summary, objective, timings, ...) and its tables (`.table(name)`, checked against run.json's
    hashes). LookupError if there is no such run, DamagedRecord if its run.json cannot be read."""
    return Run(Path(run["dir"]) if isinstance(run, pd.Series) else locate(str(run), Path(root)))


def record(run, root=DEFAULT_ROOT) -> RunRecord:
    """The typed run.json of `run` (see `open_run`): `record(run).summary.rate()`, `.status`, `.timings`, ..."""
    return open_run(run, root).record


def export_data(run, out, root=DEFAULT_ROOT) -> tuple[int, str]:
    """`rdsexp-runs export --data RUN --out FILE`: the run's identification inputs and outputs (u_k, y_k of
    every identification path) in the data format (long form CSV or parquet: path, k, u[i], y[i]; `data.py`),
    the file a data run (`rdsexp data=FILE model=NAME`) identifies from. Returns (rows written, a note).

    The identification table holds the run's last identification pass: for an open-loop identification
    every pass filters the same plant outputs, so the file replays each of them; under feedback
    (identification.feedback nominal or a gain) the input of each pass depended on that pass's estimates,
    and the file holds the last pass's record only (a data run re-filters it, it cannot re-run the plant)."""
    from .data import write
    frame = load(run, "identification", root=root)
    feedback = record(run, root).summary.identification_feedback
    m = sum(1 for c in frame.columns if c.startswith("u["))
    ny = sum(1 for c in frame.columns if c.startswith("y["))
    frame = frame.sort_values(["path", "k"], kind="stable")
    ids = frame["path"].unique()
    steps = int(frame["k"].max()) + 1
    shape = lambda cols: frame[cols].to_numpy(dtype=float).reshape(len(ids), steps, len(cols)).transpose(1, 0, 2)
    rows = write(out, shape([f"u[{i}]" for i in range(m)]), shape([f"y[{i}]" for i in range(ny)]), ids)
    used = feedback.get("used") or feedback.get("mode") or "open_loop"
    note = "open-loop identification: the file replays it exactly" if str(used).startswith(
        ("open_loop", "none", "recorded", "the recorded")) or feedback.get("mode") == "none" else \
        f"identification under feedback ({used}): the file holds the last pass's inputs and outputs"
    return rows, note


def locate(run: str, root: Path = DEFAULT_ROOT) -> Path:
    """A run directory from a path or an id; LookupError with one line if there is none."""
    return RunStore(root).locate(run)


def locate_sweep(sweep: str, root: Path = DEFAULT_ROOT) -> Path | None:
    """A sweep directory from its path, its directory name, or its config name (the latest sweep of
    that name); None if `sweep` names no sweep."""
    return RunStore(root).locate_sweep(sweep)


def diff(a: str, b: str, root=DEFAULT_ROOT) -> pd.DataFrame:
    """Differences between two runs or two sweeps, one row each: (what, key, a, b).

    Runs: every param and metric that differs, the code version and the tables whose content differs.
    Sweeps: params that are constant within each but differ between them, the swept params with
    their values, the jobs' statuses, and every metric that differs between jobs with the same swept
    values (key "metric @ param=value, ...")."""
    root = Path(root)
    sweeps = [locate_sweep(x, root) if not layout.is_run(Path(x)) else None for x in (a, b)]
    if all(sweeps):
        return _diff_sweeps(search(sweeps[0]), search(sweeps[1]))
    one, two = (search(locate(x, root).parent).pipe(lambda t, x=x: t[t["dir"] == str(locate(x, root))])
                for x in (a, b))
    keys = [c for c in [*one.columns, *two.columns] if c.startswith(("params.", "metrics."))]
    rows = _diff_rows(one.iloc[0], two.iloc[0], ["plant_hash", *sorted(keys, key=lambda c: not c.startswith(
        "params.")), "code"], skip=("metrics.seconds",))
    rows += config_entries(*(Run(locate(x, root)) for x in (a, b)), shown={r["key"] for r in rows})
    tables = {x: Run(locate(x, root)).record.tables for x in (a, b)}
    for name in sorted(set(tables[a]) | set(tables[b])):
        ha, hb = (getattr(tables[x].get(name), "sha256", None) for x in (a, b))
        if ha != hb:
            rows.append({"what": "table", "key": name, "a": (ha or "missing")[:12], "b": (hb or "missing")[:12]})
    return pd.DataFrame(rows, columns=["what", "key", "a", "b"])


CONFIG_ROWS = 20     # entries of list-valued config `diff` lists one by one, then how many more differ


def list_entries(run: Run) -> dict:
    """{key: value} of the run's composed config entries inside lists (matrices, a xi law's components:
    `plant.xi.components[0].prob`, `plant.A[2][0][0]`), which the runs table keeps only as scalars;
    {} when the config cannot be read."""
    from omegaconf import OmegaConf
    try:
        config = OmegaConf.to_container(run.config, resolve=False)
    except (OSError, ValueError):
        return {}
    found = {}

    def walk(x, key: str, in_list: bool) -> None:
        if isinstance(x, dict):
            for k, v in x.items():
                walk(v, f"{key}.{k}" if key else str(k), in_list)
        elif isinstance(x, list):
            for i, v in enumerate(x):
                walk(v, f"{key}[{i}]", True)
        elif in_list:
            found[key] = x
    walk(config, "", False)
    return found


def config_entries(a: Run, b: Run, shown: set) -> list[dict]:
    """Rows (config, key, a, b) of the config entries inside lists (`list_entries`) that differ between two
    runs (None where one run has no such entry): the first CONFIG_ROWS, then one row counting the rest.
    Keys already in `shown` are skipped."""
    one, two = list_entries(a), list_entries(b)
    found = [{"what": "config", "key": key, "a": one.get(key), "b": two.get(key)}
             for key in dict.fromkeys([*one, *two]) if key not in shown and one.get(key) != two.get(key)]
    more = [{"what": "config", "key": f"... {len(found) - CONFIG_ROWS} more entries", "a": "", "b": ""}] \
        if len(found) > CONFIG_ROWS else []
    return found[:CONFIG_ROWS] + more


def changed_entries(table: pd.DataFrame) -> pd.DataFrame:
    """Columns `config.<key>` (rows as `table`'s, by its `dir`) of the config entries inside lists
    (`list_entries`) whose value is not the same in every row: what `list --changed` adds to the params
    that vary, so that two plant files of one name show the entry that tells them apart. At most
    CONFIG_ROWS columns (the first in config order)."""
    entries = []
    for directory in table["dir"]:
        try:
            entries.append(list_entries(Run(Path(directory))))
        except DamagedRecord:
            entries.append({})
    keys = [k for k in dict.fromkeys(k for e in entries for k in e)
            if len({repr(e.get(k)) for e in entries}) > 1][:CONFIG_ROWS]
    return pd.DataFrame({f"config.{k}": [e.get(k) for e in entries] for k in keys}, index=table.index)


def _same(x, y) -> bool:
    if isinstance(x, float) and isinstance(y, float) and np.isnan(x) and np.isnan(y):
        return True
    return bool(x == y) if not (pd.isna(x) is True or pd.isna(y) is True) else (pd.isna(x) is pd.isna(y))


def _diff_rows(ra: pd.Series, rb: pd.Series, keys: list[str], suffix: str = "", skip=()) -> list[dict]:
    """Rows (what, key, a, b) of the keys whose values differ (seconds: timings are not results)."""
    rows = []
    for key in (k for k in dict.fromkeys(keys) if k not in skip):
        x, y = ra.get(key, np.nan), rb.get(key, np.nan)
        if not _same(x, y):
            what = key.split(".")[0] if "." in key else key
            rows.append({"what": what.removesuffix("s") if what in ("params", "metrics") else what,
                         "key": key.split(".", 1)[-1] + suffix, "a": x, "b": y})
    return rows


def _diff_sweeps(ta: pd.DataFrame, tb: pd.DataFrame) -> pd.DataFrame:
    rows = []
    params = sorted({c for c in [*ta.columns, *tb.columns] if c.startswith("params.")})
    swept = [p for p in params if p in changed(ta) or p in changed(tb)]
    for p in params:
        if p in swept:
            values = [sorted(t[p].astype(str).unique()) if p in t else ["missing"] for t in (ta, tb)]
            rows.append({"what": "swept", "key": p.removeprefix("params."), "a": ", ".join(values[0]),
                         "b": ", ".join(values[1])})
        else:
            x, y = (t[p].iloc[0] if p in t and len(t) else np.nan for t in (ta, tb))
            if not _same(x, y):
                rows.append({"what": "param", "key": p.removeprefix("params."), "a": x, "b": y})
    status = [", ".join(f"{n} {s}" for s, n in t["status"].value_counts().items()) for t in (ta, tb)]
    rows.append({"what": "jobs", "key": "status", "a": status[0], "b": status[1]})
    key = [p for p in swept if p in ta and p in tb]
    metrics = sorted({c for c in [*ta.columns, *tb.columns] if c.startswith("metrics.")} - {"metrics.seconds"})
    if key:
        merged = ta.astype({k: str for k in key}).merge(tb.astype({k: str for k in key}), on=key,
                                                         suffixes=("@a", "@b"))
        for _, row in merged.iterrows():
            at = " @ " + ", ".join(f"{k.removeprefix('params.')}={row[k]}" for k in key)
            ra = pd.Series({m: row.get(f"{m}@a", row.get(m, np.nan)) for m in metrics})
            rb = pd.Series({m: row.get(f"{m}@b", row.get(m, np.nan)) for m in metrics})
            rows += _diff_rows(ra, rb, metrics, at)
    return pd.DataFrame(rows, columns=["what", "key", "a", "b"])


CELL = 40      # `diff`'s table keeps its cells this short; longer texts (verdict reasons) are listed below it


def diff_text(differences: pd.DataFrame, cell: int = CELL) -> str:
    """`diff`'s table as the terminal shows it: within about 120 columns, a value longer than `cell` characters
    replaced by a note [n] and written out in full below the table."""
    notes, table = [], differences.copy()
    for column in ("a", "b"):
        def short(value, column=column):
            text = str(value)
            if len(text) <= cell:
                return value
            notes.append(f"[{len(notes) + 1}] {column}: {text}")
            return f"[{len(notes)}]"
        table[column] = [short(v) for v in table[column]]
    return table.to_string(index=False) + ("\n\n" + "\n".join(notes) if notes else "")


def compare_tables(stored: pd.DataFrame, fresh: pd.DataFrame) -> list[str]:
    """Differences between two versions of a table, column by column; [] when identical."""
    problems = []
    if list(stored.columns) != list(fresh.columns) or len(stored) != len(fresh):
        return [f"shape/columns differ: {stored.shape} {list(stored.columns)[:5]}... vs "
                f"{fresh.shape} {list(fresh.columns)[:5]}..."]
    for name in stored.columns:
        a, b = stored[name].to_numpy(), fresh[name].to_numpy()
        if a.dtype.kind in "biuf" and b.dtype.kind in "biuf":
            a, b = a.astype(float), b.astype(float)
            same = (a == b) | (np.isnan(a) & np.isnan(b))
            if not same.all():
                first = int(np.argmax(~same))
                diff = np.nanmax(np.abs(a - b)) if np.isfinite(a - b).any() else np.inf
                problems.append(f"{name}: max |difference| {diff:.3g}, first at row {first}")
        elif not np.array_equal(a.astype(str), b.astype(str)):
            problems.append(f"{name}: values differ, first at row {int(np.argmax(a.astype(str) != b.astype(str)))}")
    return problems


def verify(run_dir: Path) -> tuple[bool, list[str]]:
    """Re-execute a stored run from its recorded config and seed and compare every table: (identical,
    the report's lines). A damaged file (missing, unreadable, modified after the run) is reported
    as such and fails verify."""
    from .config import build
    from .pipeline import run_experiment
    run = Run(run_dir)
    stored, damaged = run.record, run.damage()
    lines = [f"damaged: {run_dir / problem}" for problem in damaged]
    if not (run_dir / layout.HYDRA_CONFIG).is_file():
        return False, [*lines, f"verify: cannot re-run without {layout.HYDRA_CONFIG} (damaged)"]
    from omegaconf import OmegaConf
    cfg = OmegaConf.load(run_dir / layout.HYDRA_CONFIG)
    code = provenance.code_version()["version"]
    if code != stored.code_version:
        lines.append(f"note: the run was made with code {stored.code_version}, this is {code}")
    exp = build(cfg)
    recorded_data = stored.data
    if recorded_data and exp.data is not None and exp.data.data.sha256 != recorded_data.get("sha256"):
        return False, [*lines, f"verify: the data file {exp.data.data.file} has changed since the run (sha256 "
                               f"{exp.data.data.sha256[:12]}, the run's {str(recorded_data.get('sha256'))[:12]})"]
    outcome = run_experiment(exp)
    ok = not damaged
    for name in stored.tables:
        fresh = outcome.tables.get(name)
        try:        # a modified table is reported damaged above; its differences are shown too
            stored = run.table(name, check_hash=False)
        except DamagedRecord as err:
            lines.append(f"{name:15s} DAMAGED: {err.path.name}: {err.reason}")
            ok = False
            continue
        problems = compare_tables(stored, fresh) if fresh is not None else ["not produced by the re-run"]
        lines += [f"{name:15s} {'identical' if not problems else 'DIFFERS'}", *(f"    {p}" for p in problems)]
        ok &= not problems
    return ok, [*lines, f"verify: {'identical' if ok else 'differences found'}"]


def check(root: Path, move: bool = False) -> tuple[int, list[str]]:
    """`rdsexp-runs check [DIR] [--quarantine]`: every damaged or inconsistent record under a store;
    with `move`, quarantine them and rebuild the summaries concerned. Returns (exit code: 1 when
    something was found and left in place, else 0; the report's lines)."""
    store = RunStore(root)
    findings = store.check()
    lines = [finding.line() for finding in findings]
    if not findings:
        return 0, [f"check: {root}: no damaged or inconsistent record"]
    if not move:
        return 1, [*lines, f"check: {root}: {len(findings)} damaged or inconsistent; `--quarantine` moves the "
                           f"damaged records to {Path(root) / layout.QUARANTINE} and rebuilds the summaries"]
    moves, rebuilt = store.quarantine(findings)
    lines += [f"moved {source} -> {target}" for source, target in moves] + [f"rebuilt {path}" for path in rebuilt]
    return 0, [*lines, f"check: {root}: {len(moves)} moved to quarantine, {len(rebuilt)} summaries rebuilt, "
                       f"index rebuilt"]


def _report(result: tuple) -> int:
    """Print a command's lines; its exit code (0 for True)."""
    status, lines = result
    print("\n".join(lines))
    return status if isinstance(status, int) and not isinstance(status, bool) else int(not status)


def main(argv=None, commands: dict | None = None) -> int:
    """`rdsexp-runs`: parse argv and run the command; its exit code. commands: more subcommands from
    the layers above (`rdsexp.runs` adds `plot`), {name: (help, add_arguments(parser), run(args) -> int)}."""
    parser, sub = _parser()
    for name, (text, add_arguments, _) in (commands or {}).items():
        add_arguments(sub.add_parser(name, help=text))
    args = parser.parse_args(argv)
    try:
        with warnings_as_lines():
            if args.command in (commands or {}):
                return commands[args.command][2](args)
            return _command(args)
    except (ValueError, LookupError) as err:
        print(f"rdsexp-runs: {err}", file=sys.stderr)
        return 2


def _parser():
    parser = argparse.ArgumentParser(prog="rdsexp-runs", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_list = sub.add_parser("list", help="table of runs under DIR (default outputs/)")
    p_list.add_argument("dir", nargs="?", default=str(DEFAULT_ROOT))
    p_list.add_argument("--where", help='filter, e.g. "enkf.q_scale >= 1 and status == \'complete\'"')
    p_list.add_argument("--sort", help="column to sort by (--sort=-NAME: descending)")
    p_list.add_argument("--columns", help="comma-separated columns (params./metrics. prefix optional; all: every one)")
    p_list.add_argument("--changed", action="store_true",
                        help="also the params, and the config entries inside lists (plant matrices, xi components), "
                             "that vary between the runs")
    p_list.add_argument("--csv", action="store_true", help="CSV with full column names")
    p_list.add_argument("--all", action="store_true",
                        help="also the sweep jobs that reused a listed run (each computation is listed once without)")
    p_check = sub.add_parser("check", help="list damaged or inconsistent records under DIR (default outputs/)")
    p_check.add_argument("dir", nargs="?", default=str(DEFAULT_ROOT))
    p_check.add_argument("--quarantine", action="store_true",
                         help="move damaged records to DIR/quarantine/ (nothing is deleted), rebuild summaries")
    for name, text in (("show", "run.json and metrics of a run, or a sweep's jobs"),
                       ("verify", "re-run and compare tables"), ("view", "open the recording(s) in the Rerun viewer")):
        p = sub.add_parser(name, help=text)
        p.add_argument("run")
        p.add_argument("--root", default=str(DEFAULT_ROOT))
    p_diff = sub.add_parser("diff", help="config and metric differences of two runs or two sweeps")
    p_diff.add_argument("a")
    p_diff.add_argument("b")
    p_diff.add_argument("--root", default=str(DEFAULT_ROOT))
    return parser, sub


def _command(args) -> int:
    if args.command == "list":
        table = search(Path(args.dir), args.where, copies=args.all)
        if not len(table):
            print(f"no runs under {args.dir}" + (f" with {args.where}" if args.where else ""))
            return 0
        if args.sort:
            key = column(table, args.sort.lstrip("-"))
            table = table.sort_values(key, ascending=not args.sort.startswith("-"), kind="stable")
        if args.columns == "all":
            cols = list(table.columns)
        varying = []                          # with --changed: the params, then the list entries, that vary
        if args.changed:
            entries = changed_entries(table)
            table, varying = pd.concat([table, entries], axis=1), [*changed(table), *entries.columns]
        elif not args.columns:
            varying = ["params.gain.method"]
        if args.columns == "all":
            cols = list(table.columns)
        elif args.columns:                    # with --changed, what varies follows the columns asked for
            cols = [column(table, c.strip()) for c in args.columns.split(",") if c.strip()]
            cols = list(dict.fromkeys([*cols, *varying]))
        else:
            cols = [*IDENTITY_SHOWN, *varying, *listed_columns(table)]
            cols = [c for c in dict.fromkeys(cols) if c in table.columns]
        _print(table[cols], args.csv)
        return 0
    if args.command == "check":
        return _report(check(Path(args.dir), move=args.quarantine))
    if args.command == "diff":
        differences = diff(args.a, args.b, Path(args.root))
        print(diff_text(differences) if len(differences) else "no differences")
        return 0
    root = Path(args.root)
    sweep = locate_sweep(args.run, root) if not layout.is_run(Path(args.run)) else None
    if args.command == "view":
        return view(sweep if sweep is not None else locate(args.run, root))
    if sweep is not None and args.command == "show":
        show_sweep(sweep)
        return 0
    run_dir = locate(args.run, root)
    try:
        run = Run(run_dir)
    except DamagedRecord as err:
        print(f"rdsexp.runs: damaged: {err}", file=sys.stderr)
        return 1
    if args.command == "show":
        from omegaconf import OmegaConf

        from .store.table import identity
        who = identity(run_dir, run.record)             # the catalog's identity of the run, first
        job = f" job {who['job']}" if who["job"] is not None else ""
        reused = f", reused from {who['reused_from']}" if who["reused_from"] else ""
        plant = who["plant"] if not who["plant_hash"] else f"{who['plant']}@{who['plant_hash'][:6]}"
        print(f"run {who['id']}: plant {plant} (model {who['model']}), sweep {who['sweep'] or MISSING}{job}, "
              f"seed {who['seed']}, overrides {who['overrides'] or '(none)'}{reused}")
        print(OmegaConf.to_yaml(run.shown()))
        for problem in run.damage() if run.record.complete else []:
            print(f"damaged: {run_dir / problem}")
        if "metrics" in run.record.tables:
            try:
                print(run.table("metrics").to_string(index=False))
            except DamagedRecord:
                pass                                  # named above
        return 0
    return _report(verify(run_dir))


def listed_columns(table: pd.DataFrame) -> list[str]:
    """The registry's listed metrics (`metrics.listed`) among the table's columns: a run's own wherever the
    column is; a tuning trial's objective (mean over its seeds and standard error, on the trial's first run,
    and the held-out re-run's on its last) only where a run of the table has one."""
    return [m.column for m in metrics.listed() if m.column in table.columns
            and (m.source != metrics.OBJECTIVE or table[m.column].notna().any())]


def _print(table: pd.DataFrame, csv: bool) -> None:
    """A search table as text (short column names, 4 significant digits) or as CSV (full names)."""
    if csv:
        sys.stdout.write(table.to_csv(index=False))
        return
    print(as_text(table))


def show_sweep(sweep_dir: Path) -> None:
    """The sweep's directory, name, command-line overrides, job statuses and per job the swept params
    and key metrics."""
    table = search(sweep_dir)
    from omegaconf import OmegaConf
    cfg = OmegaConf.load(sweep_dir / layout.MULTIRUN) if (sweep_dir / layout.MULTIRUN).exists() else None
    overrides = list(OmegaConf.select(cfg, "hydra.overrides.task") or []) if cfg is not None else []
    names = sorted(set(table["sweep"].dropna())) if len(table) else []
    print(f"sweep {sweep_dir.name}: {', '.join(names) or 'unnamed'}, {len(table)} jobs "
          f"({', '.join(f'{n} {s}' for s, n in table['status'].value_counts().items()) if len(table) else 'none'})")
    print(f"  directory: {sweep_dir}")
    print(f"  overrides: {' '.join(overrides) or '(none)'}")
    if (sweep_dir / layout.SUMMARY_RECORDING).exists():
        print(f"  view: rdsexp-runs view {sweep_dir}")
    if len(table):
        _print(sweep_results(table), csv=False)


def view(target: Path) -> int:
    """Open a run's recording.rrd, or a sweep's summary.rrd, in the Rerun viewer; without a display
    (or without the `rerun` command) print the command instead."""
    name = layout.RECORDING if layout.is_run(target) else layout.SUMMARY_RECORDING
    path = target / name
    if not path.exists():
        print(f"rdsexp-runs: no {name} in {target} (tracking.recording=false, or a sweep without a summary)",
              file=sys.stderr)
        return 1
    exe = shutil.which("rerun")
    command = [exe or "rerun", str(path)]
    display = sys.platform in ("darwin", "win32") or os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    if exe is None or not display:
        print(" ".join(command))
        return 0
    return subprocess.call(command)


if __name__ == "__main__":
    sys.exit(main())
