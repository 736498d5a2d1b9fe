"""The round trip of README "Your own data" on every plant of the library: a small run, its identification
exported (`rdsexp-runs export --data`), identified again from the file (`rdsexp data=FILE model=NAME`, NAME a
model file with the plant's bases and its xi as the prior guess, and the plant's settings lines), and the
largest difference of the modeled moments (model table) printed with how the run was identified.

    python experiments/data_round_trip.py [--plants paper dropout ...]

Open-loop identifications (every pass filters the same outputs) replay exactly; one under feedback ran its
plant again in each pass with inputs that depended on that pass's estimates, and the file holds the last
pass only, so its moments differ.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from rdsexp import runs

REPO = Path(__file__).resolve().parents[1]
SMALL = ["closed_loop.paths=4", "enkf.ensemble_size=20", "closed_loop.horizon=30", "closed_loop.rate_window=[10,20]",
         "closed_loop.disturbance.until=10", "identification.horizon=30", "identification.K0=5",
         "identification.K1=20"]


def rdsexp(*args, cwd, module="rdsexp"):
    subprocess.run([sys.executable, "-m", module, *args], cwd=cwd, check=True, capture_output=True, text=True)


def round_trip(plant: str, tmp: Path) -> dict:
    cwd = tmp / plant
    (cwd / "conf" / "model").mkdir(parents=True)
    rdsexp(f"plant={plant}", *SMALL, cwd=cwd)
    (original,) = list((cwd / "outputs" / "runs").iterdir())
    rdsexp("export", "--data", str(original), "--out", "d.csv", cwd=cwd, module="rdsexp.runs")
    spec = yaml.safe_load((REPO / "conf" / "plant" / f"{plant}.yaml").read_text())
    model = "paper" if plant == "paper" else f"{plant}_model"
    if plant != "paper":       # the plant's own structure, its xi as the prior guess
        (cwd / "conf" / "model" / f"{model}.yaml").write_text(yaml.safe_dump(
            {"name": model, **{k: spec.get(k) for k in ("A", "B", "C", "D")}, "xi": spec["xi"]}))
    rdsexp("--config-dir", str(cwd / "conf"), "data=d.csv", f"model={model}", f"plant={plant}", *SMALL, cwd=cwd)
    (data_run,) = [r for r in (cwd / "outputs" / "runs").iterdir() if r != original]
    a, b = (pd.read_parquet(r / "model.parquet")["value"].to_numpy() for r in (original, data_run))
    feedback = runs.record(original).summary.identification_feedback
    return {"plant": plant, "identification": feedback.get("used") or feedback.get("mode"),
            "max_difference": float(np.max(np.abs(a - b))) if a.shape == b.shape else float("nan")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plants", nargs="*", default=sorted(p.stem for p in (REPO / "conf" / "plant").glob("*.yaml")
                                                                    if p.stem != "recorded"))
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        rows = [round_trip(plant, Path(tmp)) for plant in args.plants]
    print(pd.DataFrame(rows).to_string(index=False))


if __name__ == "__main__":
    main()
