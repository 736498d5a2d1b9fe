"""Holdout validation of data runs on the library's `dropout` and `two_carts` and on random plants
(experiments/random_plants.py): the modeled law of xi against the nominal model (xi at its mean) on held-out
recorded paths, one step ahead (README "Your own data").

    python experiments/data_validation.py [--random 10] [--seed 0] [--paths 50]

Per plant: `paths` recorded experiments of 101 steps (k = 0..100) simulated from the plant file (its true law
of xi), each driven by conf/identification's input (an M-sequence in {0, 10}) under a stabilizing gain designed
at the mean (`nominal_gain`) when the plant is open-loop mean-square unstable at it, in open loop otherwise (the
library's `auto`), observed by an EnKF on the plant's structure; the applied u_k and y_k saved in the data
format. Then `rdsexp data=FILE model=M plant=recorded data.holdout=0.2` with M the plant's bases and its xi law
as the prior guess, and the run's validation (CRPS, coverage of the 50% and 90% intervals) printed per plant.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from rdsexp import runs
from rdsexp.experiment.data import write
from rdsexp.numerics.analysis import ms_rate
from rdsexp.numerics.distributions import from_spec
from rdsexp.numerics.enkf import EnKF
from rdsexp.numerics.modeling import mls_input, nominal_gain
from rdsexp.numerics.simulation import simulate
from rdsexp.numerics.systems import AffineRandomSystem, MomentModel

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "experiments"))


def record(content: dict, out: Path, paths: int, seed: int) -> dict:
    """Simulate `paths` recorded experiments of the plant file content into `out`; how they were run."""
    dist = from_spec(content["xi"])
    plant = AffineRandomSystem(content["A"], content["B"], content.get("C"), content.get("D"), xi_dist=dist)
    mean = MomentModel.deterministic(dist.mean)
    F, how = None, "open_loop"
    if not ms_rate(plant, mean, np.zeros((plant.m, plant.n))) < 1:
        res = nominal_gain(plant, dist.mean)
        if res.F is not None and res.lam < 1:
            F, how = res.F, "nominal feedback"
    n, p = plant.n, plant.p
    observer = EnKF(plant, Q=np.diag([1e-4] * n + [0.0] * p), R=1e-4 * np.eye(plant.ny))
    tr = simulate(plant, observer, F=F, d=mls_input(100, plant.m, 7, 10.0, levels="unipolar"), q0=np.zeros(n),
                  psi0=np.r_[np.zeros(n), dist.mean], ensemble_size=20, paths=paths, seed=seed)
    ok = tr.failed_at < 0
    write(out, tr.u[:, ok], tr.y[:, ok])
    return {"recorded_under": how, "recorded_paths": int(ok.sum())}


def validate(name: str, content: dict, tmp: Path, paths: int, seed: int) -> dict:
    conf = tmp / name
    (conf / "model").mkdir(parents=True)
    (conf / "plant").mkdir()
    (conf / "plant" / "recorded.yaml").write_text("name: recorded\n")
    (conf / "model" / f"{name}.yaml").write_text(yaml.safe_dump(
        {"name": name, **{k: content.get(k) for k in ("A", "B", "C", "D")}, "xi": content["xi"]}))
    info = record(content, conf / "data.csv", paths, seed)
    proc = subprocess.run([sys.executable, "-m", "rdsexp", "--config-dir", str(conf), f"data={conf / 'data.csv'}",
                           f"model={name}", "plant=recorded", "data.holdout=0.2", "tracking.recording=false"],
                          cwd=conf, capture_output=True, text=True)
    row = {"plant": name, **info}
    if proc.returncode != 0:
        return row | {"error": (proc.stderr.strip().splitlines() or ["?"])[-1]}
    (run_dir,) = list((conf / "outputs" / "runs").iterdir())
    stored = runs.record(run_dir)          # the validation's numbers are catalog metrics validation_<law>_<number>
    if "metrics.validation_modeled_better" not in stored.metrics:
        return row | {"error": stored.summary.modeling_status}
    return row | {f"{law}_{k}": round(stored.metric(f"validation_{law}_{k}"), 4) for law in ("modeled", "nominal")
                  for k in ("crps", "coverage_50", "coverage_90")} | {"modeled_better": stored.metric(
                      "validation_modeled_better")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--random", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--paths", type=int, default=50)
    args = parser.parse_args()
    plants = {name: yaml.safe_load((REPO / "conf" / "plant" / f"{name}.yaml").read_text())
              for name in ("dropout", "two_carts")}
    if args.random:
        from random_plants import draw_plants
        plants |= {p.name: p.content for p in draw_plants(args.random, args.seed)}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, content in plants.items():
            rows.append(validate(name, content, Path(tmp), args.paths, args.seed))
            print(json.dumps(rows[-1]), flush=True)
    print(pd.DataFrame(rows).to_string(index=False))


if __name__ == "__main__":
    main()
