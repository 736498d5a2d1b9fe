"""Regenerate every figure and table of the report into outputs/report/ from stored runs.

    python experiments/paper.py [--root outputs] [--out outputs/report] [--allow-mixed]

Finds the latest stored `paper`, `ensemble_size`, `noise` and `window` sweeps under --root; a
missing one is run first (`python -m rdsexp +sweep=NAME`, said on the terminal). Then every
figure and table is drawn from the stored parquet tables only; re-running on the same runs
rewrites identical files and simulates nothing. Refuses runs of different code versions unless
--allow-mixed.
"""
import subprocess
import sys

import fig_decay
import fig_estimation
import fig_gains
import fig_sweeps
import reproduction_table

from rdsexp import report

SWEEPS = ("paper", "ensemble_size", "noise", "window")


def ensure_sweeps(root, extra_overrides=()) -> None:
    for sweep in SWEEPS:
        if not report.load_runs(root, sweep):
            print(f"no stored runs of sweep {sweep!r} under {root}: running python -m rdsexp +sweep={sweep}",
                  flush=True)
            sweep_dir = f"hydra.sweep.dir={root.resolve()}/sweeps/${{now:%Y-%m-%d_%H-%M-%S-%f}}_${{uid:}}"
            subprocess.run([sys.executable, "-m", "rdsexp", f"+sweep={sweep}", sweep_dir, *extra_overrides],
                           check=True)


def main(argv=None) -> None:
    args = report.arguments(__doc__.splitlines()[0], argv)
    ensure_sweeps(args.root)
    common = ["--root", str(args.root), "--out", str(args.out)] + (["--allow-mixed"] if args.allow_mixed else [])
    for script in (fig_estimation, fig_decay, fig_gains, fig_sweeps):
        script.main(common)
    table = reproduction_table.main(common)
    print(table["verdict"].value_counts().to_string())
    print(f"report written to {args.out}/")


if __name__ == "__main__":
    main()
