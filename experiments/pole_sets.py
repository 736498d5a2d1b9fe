"""Pole placement with other poles (Sec. V-B: "a similar comment also applies to the cases with other poles").

For each plant (default: every plant in conf/plant/), a seeded sample of pole sets inside the unit
disc (`random_pole_sets`: conjugate pairs and real poles, uniform in area) is placed on the mean (LTI)
model, and each gain's exact mean-square rate on the TRUE plant is computed (sqrt(rho(E[Acl (x) Acl])),
ideal state feedback, no Monte Carlo). Design bases: the model with xi fixed to the mean of its
true distribution (`true_mean`, from the plant's own law through `truth_map`) and, where the plant
file gives them, the paper's reported moments (`reported`, what the paper designed from). Exact rates,
so the fractions are exact for the sample; the interval is Clopper-Pearson 95% for the probability
under the sampling law.

Tables: pole_sets.{csv,md} (per plant and basis: sets, fraction mean-square stabilizing on the true
plant, interval, fraction beating the proposed gain's rate, best and median rate, the plant file's
own poles for comparison) and pole_sets_all.csv (every set, its poles and rates).

    python experiments/pole_sets.py [--plants paper,other] [--count 200] [--seed 0] [--out outputs/report]
"""
from __future__ import annotations

import argparse
import importlib.resources
import zlib
from pathlib import Path

import numpy as np
import pandas as pd
from hydra import compose, initialize_config_module
from scipy import stats

import rdsexp as rx
from rdsexp import report
from rdsexp.experiment.config import build
from rdsexp.experiment.store import files
from rdsexp.numerics.analysis import ms_rate
from rdsexp.numerics.enkf import truth_map
from rdsexp.numerics.synthesis.classical import random_pole_sets

NAME, ALL_NAME = "pole_sets", "pole_sets_all"


def library_plants() -> list[str]:
    """Names of the plant files shipped in conf/plant/ (`recorded`, a data run's settings, has no system)."""
    folder = importlib.resources.files("rdsexp.conf") / "plant"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml") and p.name != "recorded.yaml")


def experiment(plant: str):
    """The validated Experiment of conf/ with plant=PLANT (everything else default)."""
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        return build(compose("config", overrides=[f"plant={plant}"]))


def bases(exp) -> dict:
    """Design moments of the model: true_mean (the plant's law mapped to the model's xi) and reported."""
    out = {}
    plant_dist = exp.plant.check_distribution(None)
    mapped = truth_map(exp.model, exp.plant)
    if mapped is not None:
        T, t = mapped
        out["true_mean"] = rx.MomentModel(mean=T @ plant_dist.mean + t, cov=T @ plant_dist.cov @ T.T)
    if exp.reported is not None:
        out["reported"] = exp.reported
    return out


def rate(system, dist, F) -> float:
    """Exact mean-square rate, inf for a gain so large that the operator overflows."""
    try:
        with np.errstate(all="ignore"):
            value = ms_rate(system, dist, F)
    except (ValueError, np.linalg.LinAlgError):
        return float("inf")
    return value if np.isfinite(value) else float("inf")


def place(exp, dist, poles) -> tuple[np.ndarray | None, str]:
    """Pole-placement gain on the mean model (None and the reason when scipy cannot place them)."""
    try:
        return rx.synthesize(exp.model, dist, "pole_placement", poles=poles).F, "designed"
    except ValueError as err:                      # e.g. (A, B) not controllable at the mean
        return None, f"not placed: {err}"


def study(plant: str, count: int, seed: int) -> tuple[list[dict], list[dict]]:
    """(summary rows, per-set rows) of one plant."""
    exp = experiment(plant)
    # one child stream per plant, so adding a plant does not change another plant's sample
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(zlib.crc32(plant.encode()),)))
    sets = random_pole_sets(rng, exp.model.n, count)
    summary, rows = [], []
    own = exp.design.options_by_method.get("pole_placement", {}).get("poles")
    for basis, dist in bases(exp).items():
        proposed = rx.synthesize(exp.model, dist, "proposed")
        proposed_rate = rate(exp.plant, None, proposed.F) if proposed.F is not None else np.nan
        rates = []
        for i, poles in enumerate(sets):
            F, status = place(exp, dist, poles)
            r_plant = rate(exp.plant, None, F) if F is not None else np.nan
            r_model = rate(exp.model, dist, F) if F is not None else np.nan
            rates.append(r_plant)
            rows.append({"plant": plant, "basis": basis, "set": i, "poles": np.round(poles, 6).tolist().__str__(),
                         "pole_radius": float(np.abs(poles).max()), "status": status,
                         "rate_design": rate(exp.model, rx.MomentModel.deterministic(dist.mean), F)
                         if F is not None else np.nan,
                         "rate_model": r_model, "rate_plant": r_plant})
        rates = np.array(rates)
        stable = int(np.sum(rates < 1))
        lo, hi = stats.binomtest(stable, count).proportion_ci(0.95, method="exact")
        F_own = place(exp, dist, own)[0] if own is not None else None
        summary.append({"plant": plant, "basis": basis, "sets": count, "seed": seed,
                        "placed": int(np.sum(np.isfinite(rates))), "ms_stabilizing": stable,
                        "ms_stabilizing_fraction": stable / count, "fraction_low": lo, "fraction_high": hi,
                        "beats_proposed": int(np.sum(rates < proposed_rate)),
                        "best_rate_plant": float(np.nanmin(rates)), "median_rate_plant": float(np.nanmedian(rates)),
                        "proposed_rate_plant": proposed_rate,
                        "own_poles_rate_plant": rate(exp.plant, None, F_own) if F_own is not None else np.nan})
    return summary, rows


def main(argv=None) -> pd.DataFrame:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plants", default=None, help="comma-separated conf/plant names (default: all)")
    parser.add_argument("--count", type=int, default=200, help="pole sets per plant (default 200)")
    parser.add_argument("--seed", type=int, default=0, help="root seed of the sample (default 0)")
    parser.add_argument("--out", type=Path, default=Path("outputs/report"))
    args, _ = parser.parse_known_args(argv)        # the report's --root / --allow-mixed are not used here
    plants = args.plants.split(",") if args.plants else library_plants()
    extra = {"seed": args.seed, "count": args.count, "plants": plants}
    record = report.lineage([], __file__, outputs=[f"{NAME}.csv", f"{NAME}.md"], **extra)
    if report.up_to_date(args.out, NAME, record) and (args.out / f"{ALL_NAME}.csv").exists():
        summary = pd.read_csv(args.out / f"{NAME}.csv")      # the same code, sample and plants made it
        print(summary.to_string(index=False))
        return summary
    summary, rows = [], []
    for plant in plants:
        s, r = study(plant, args.count, args.seed)
        summary += s
        rows += r
    summary = pd.DataFrame(summary)
    report.write_table(summary, args.out, NAME, [], __file__, **extra)
    files.atomic_write_bytes(args.out / f"{ALL_NAME}.csv", pd.DataFrame(rows).to_csv(index=False).encode())
    print(summary.to_string(index=False))
    return summary


if __name__ == "__main__":
    report.script(main)
