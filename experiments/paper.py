"""Regenerate every figure and table of the report into outputs/report/ from stored runs.

    python experiments/paper.py [--root outputs] [--out outputs/report] [--allow-mixed] [--jobs N]

Finds the latest stored `paper`, `ensemble_size`, `noise`, `window`, `identification_input` and
`closed_loop_rate` sweeps under --root; a missing one is run first (`python -m rdsexp
+sweep=NAME`, said on the terminal). The pole_sets study (exact rates of pole-placement gains, no
Monte Carlo) is computed from the configs; the robust_width figure and table are drawn when its sweep
is stored (`python -m rdsexp +sweep=robust_width`), and so are the filters and online-control
studies (`+sweep=filters`, `+sweep=controllers`, `+sweep=online`, per plant). Then every figure
and table is drawn from the stored parquet tables only; re-running on the same runs rewrites
identical files and simulates nothing. Refuses runs of different code versions unless
--allow-mixed. Last, index.md: one page with every figure (in the paper's order, then any other
figure present with its table), its caption and the tables, then every other table.
"""
import os
import subprocess
import sys
from pathlib import Path

import closed_loop_rate
import fig_decay
import fig_estimation
import fig_filters
import fig_gains
import fig_online
import fig_sweeps
import identification_input
import pandas as pd
import pole_sets
import reproduction_table
import robust_width

from rdsexp import report
from rdsexp.experiment.store import files

SWEEPS = ("paper", "ensemble_size", "noise", "window", "identification_input", "closed_loop_rate")
# (kind, name, heading) in the paper's order (Sec. V-A, V-B), then rdsexp's own analyses
PAGE = (("figure", "estimation", "Identification run (Sec. V-A, Fig. estimation)"),
        ("table", "identification_input", "Which identification input matches the paper's modeled moments"),
        ("figure", "decay_proposed", "Closed loop with the proposed gain (Fig. decay_proposed)"),
        ("figure", "decay_open", "Open-loop plant (Fig. decay_open)"),
        ("table", "closed_loop_rate", "The closed-loop rate k = 60..80 by gain source and EnKF input"),
        ("figure", "gain_comparison", "Gain comparison (Sec. V-B)"),
        ("table", "gain_comparison", None),
        ("table", "pole_sets", "Pole placement with other poles (Sec. V-B), exact rates"),
        ("figure", "robust_width", "Robust box design against the box width (Sec. V-B)"),
        ("table", "robust_width", None),
        ("table", "reproduction_inputs", "Paper vs rdsexp: inputs configured as the paper says"),
        ("table", "reproduction", "Paper vs rdsexp: results computed"),
        ("figure", "sweeps", "Sweeps beyond the paper"))


def launcher(jobs: int) -> list[str]:
    """The overrides that run a sweep's jobs in `jobs` worker processes (Hydra's joblib launcher, the
    shipped sweeps' own with n_jobs=jobs; the tables are identical to the basic launcher's,
    tests/experiment/test_sweep.py); for 1, the basic launcher: one after the other in one process."""
    return ["hydra/launcher=basic"] if jobs <= 1 else ["hydra/launcher=joblib", f"hydra.launcher.n_jobs={jobs}"]


def ensure_sweeps(root, extra_overrides=(), jobs: int = 1) -> None:
    """Run every sweep of SWEEPS that has no stored runs, in `jobs` processes, saying which (i of n);
    each sweep shows its own bar of jobs done out of total with the time left."""
    for i, sweep in enumerate(SWEEPS, 1):
        if report.load_runs(root, sweep):
            print(f"[{i}/{len(SWEEPS)}] sweep {sweep}: stored", flush=True)
            continue
        print(f"[{i}/{len(SWEEPS)}] no stored runs of sweep {sweep!r} under {root}: running python -m rdsexp "
              f"+sweep={sweep}", flush=True)
        command = ["-m", "rdsexp", f"+sweep={sweep}", f"store={root.resolve()}", *launcher(jobs), *extra_overrides]
        code = subprocess.run([sys.executable, *command]).returncode
        if code != 0:          # its own lines above say why; the jobs it completed are stored and kept
            raise report.LineageError(f"sweep {sweep!r} ended with exit code {code} (its output above): the report "
                                      f"needs all of it; `python {' '.join(command)}` resumes it (only the jobs "
                                      f"not stored run), then run this script again")


def stage_totals(runs: list[report.Run]) -> pd.Series:
    """Seconds per stage summed over the runs that computed (a reused job's timings are its original's,
    counted once), from run.json's timings; the total last."""
    computed = [r for r in runs if not r.record.reused_from]
    totals: dict[str, float] = {}
    for r in computed:
        for stage, seconds in r.record.timings.items():
            if isinstance(seconds, (int, float)):            # not the per-method breakdown of synthesis
                totals[stage] = totals.get(stage, 0.0) + seconds
    series = pd.Series(totals, dtype=float).sort_values(ascending=False)
    total = float(sum(r.record.seconds or 0 for r in computed))
    return pd.concat([series[series > 0], pd.Series({"total": total})])


def index(out: Path, counts) -> str:
    """outputs/report/index.md: every figure with its caption and every table, in PAGE order."""
    lines = ["# rdsexp: reproduction of Hosoe & Peaucelle, Sec. V", "",
             "Every figure and table below is drawn from stored runs (see each output's .json for the runs, "
             "table hashes and code version). Verdicts of the computed results: "
             + ", ".join(f"{v} {n}" for v, n in counts.items()) + " (configured inputs carry no verdict).", ""]
    known = {name for kind, name, _ in PAGE if kind == "figure"}
    others = [entry for n in sorted(p.stem for p in out.glob("*.png")) if n not in known
              for entry in (("figure", n, n.replace("_", " ")), ("table", n, None))]
    shown = {name for _, name, _ in [*PAGE, *others]}       # then every other table, e.g. a study's per plant
    tables = sorted(p.stem for p in out.glob("*.md") if "." not in p.stem and p.stem != "index" and p.stem not in shown)
    others += [("table", n, n.replace("_", " ")) for n in tables]
    captioned = set()
    for kind, name, heading in [*PAGE, *others]:
        path = out / (f"{name}.png" if kind == "figure" else f"{name}.md")
        if not path.exists():
            continue
        if heading:
            lines += [f"## {heading}", ""]
        cap = out / f"{name}.caption.md"
        if kind == "figure":
            lines += [f"![{name}]({name}.png)", ""]
        else:
            lines += [path.read_text().strip(), ""]
        if cap.exists() and name not in captioned:
            lines += [f"*{cap.read_text().strip()}*", ""]
            captioned.add(name)
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = report.parser(__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                        help="worker processes for the sweeps it runs (default: every core; 1: one after the other)")
    args = parser.parse_args(argv)
    ensure_sweeps(args.root, jobs=args.jobs)
    common = ["--root", str(args.root), "--out", str(args.out)] + (["--allow-mixed"] if args.allow_mixed else [])
    for script in (fig_estimation, fig_decay, fig_gains, fig_sweeps, identification_input, closed_loop_rate,
                   pole_sets):
        script.main(common)
    stored = report.load_runs(args.root)
    if any(report.sweep_of(r) == robust_width.SWEEP for r in stored):
        robust_width.main(common)
    if fig_filters.latest_per_plant(stored):         # the filters and online-control studies, when stored
        fig_filters.main(common)                     # (not run here: 200 runs per plant)
    if any(report.latest_per_plant(stored, sweep, ("seed",)) for sweep in ("controllers", "online")):
        fig_online.main(common)
    _, results = reproduction_table.main(common)
    counts = reproduction_table.verdict_counts(results)
    files.atomic_write_bytes(args.out / "index.md", index(args.out, counts).encode())
    print(counts.to_string())
    runs = [r for sweep in SWEEPS for r in report.load_runs(args.root, sweep)]
    print(f"compute of the {sum(not r.record.reused_from for r in runs)} runs behind the report, seconds "
          f"by stage:\n" + stage_totals(runs).round(1).to_string())
    print(f"report written to {args.out}/ (one page: {args.out}/index.md)")


if __name__ == "__main__":
    report.script(main)
