"""Fingerprints of what runs compute, to prove a refactoring changes no byte of any result.

Runs a fixed set of cases (the paper, every library plant, the online controller, data runs, fallbacks and
variants), each with `python -m rdsexp ... tracking=summary` in a fresh store, and prints one JSON object:
per case, the sha256 of every table (its columns, dtypes and values), of run.json's summary, of the console
text (run directory and times taken out). Compare two of them:

    python experiments/fingerprint.py > before.json      # at the old commit
    python experiments/fingerprint.py > after.json       # at the new one
    python experiments/fingerprint.py --compare before.json after.json

Times, paths of this machine and provenance are not fingerprinted; everything a run computed is.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parent.parent
DATA = REPO / "examples" / "dropout"
FAST = ["closed_loop.paths=40", "tracking=summary"]
CASES = {
    "paper": [],
    "cart_pole": ["plant=cart_pole"],
    "dropout": ["plant=dropout"],
    "multiplicative": ["plant=multiplicative"],
    "two_carts": ["plant=two_carts"],
    "paper_designs_all": ["gain.designs=all"],
    "paper_fallback": ["gain.lmi_max_n=2"],
    "paper_iterated": ["identification.xi_model=iterated", "identification.passes=2"],
    "paper_model_observer": ["closed_loop.observer_xi=model", "closed_loop.rate_window=auto"],
    "paper_full": ["tracking=full", "closed_loop.paths=6"],
    "online": ["controller=online"],
    "online_dropout": ["controller=online", "plant=dropout"],
    "data": ["--config-dir", str(DATA), f"data={DATA / 'dropout.csv'}", "model=dropout", "plant=recorded",
             "data.holdout=0.2"],
    "data_loops": ["--config-dir", str(DATA), f"data={DATA / 'dropout.csv'}", "model=dropout", "plant=recorded",
                   "data.loops=true"],
}


def table_hash(frame: pd.DataFrame) -> str:
    """sha256 of a table's column names, dtypes and values (row order included)."""
    h = hashlib.sha256()
    h.update(json.dumps([[str(c), str(t)] for c, t in frame.dtypes.items()]).encode())
    h.update(pd.util.hash_pandas_object(frame, index=True).to_numpy().tobytes())
    return h.hexdigest()


def text_hash(value) -> str:
    return hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()


def run_case(args: list[str]) -> dict:
    with tempfile.TemporaryDirectory() as work:
        proc = subprocess.run([sys.executable, "-m", "rdsexp", *args, *FAST], cwd=work, capture_output=True, text=True)
        if proc.returncode != 0:
            return {"exit": proc.returncode, "stderr": proc.stderr[-2000:]}
        run = next(Path(work, "outputs", "runs").glob("*/run.json")).parent
        record = json.loads((run / "run.json").read_text())
        console = re.sub(r"\S*outputs/runs/\S+", "RUN", proc.stdout)
        console = re.sub(r"rdsexp run \S+", "rdsexp run RUN", console)
        console = re.sub(r"\d+(\.\d+)? ?s\b", "T s", console)
        tables = {p.stem: table_hash(pd.read_parquet(p)) for p in sorted(run.glob("*.parquet"))}
        summary = record["summary"]
        return {"tables": tables, "summary": text_hash(summary), "console": text_hash(console),
                "status": record["status"],
                "summary_json": json.loads(json.dumps(summary, default=str)), "console_text": console}


def compare(before: dict, after: dict) -> int:
    bad = 0
    for case in sorted(set(before) | set(after)):
        a, b = before.get(case), after.get(case)
        if a is None or b is None:
            print(f"{case}: only in {'after' if a is None else 'before'}")
            bad += 1
            continue
        diffs = [f"table {t}" for t in sorted(set(a.get("tables", {})) | set(b.get("tables", {})))
                 if a.get("tables", {}).get(t) != b.get("tables", {}).get(t)]
        diffs += [k for k in ("summary", "console", "status", "exit") if a.get(k) != b.get(k)]
        print(f"{case}: {'identical' if not diffs else 'DIFFERS: ' + ', '.join(diffs)}")
        if "summary" in diffs:
            sa, sb = a["summary_json"], b["summary_json"]
            for k in sorted(set(sa) | set(sb)):
                if sa.get(k) != sb.get(k):
                    print(f"    summary[{k!r}]: {sa.get(k)!r} -> {sb.get(k)!r}")
        bad += bool(diffs)
    return 1 if bad else 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--compare", nargs=2, metavar=("BEFORE", "AFTER"))
    parser.add_argument("--cases", nargs="*", default=list(CASES), help="a subset of: " + ", ".join(CASES))
    args = parser.parse_args()
    if args.compare:
        return compare(*(json.loads(Path(p).read_text()) for p in args.compare))
    out = {}
    for case in args.cases:
        out[case] = run_case(CASES[case])
        print(f"{case}: {'ok' if 'tables' in out[case] else out[case]}", file=sys.stderr)
    json.dump(out, sys.stdout, indent=1, default=lambda v: float(v) if isinstance(v, np.floating) else str(v))
    return 0


if __name__ == "__main__":
    sys.exit(main())
