"""Is "loses more paths" a finding or chance? Each loop against itself with its EnKF noise drawn anew.

`controller=online` runs the online loop beside the offline one on the same plant samples, and the run records
the paths each loop lost alone with the exact paired sign test of online losing more (`verdict.paired_losses`).
This script measures how often two bare counts of lost paths, and that test, call a loop worse than itself.
Per random plant of `random_plants.py`'s draws (--seeds, --n plants each, --paths paths), two in-process runs
with `controller=online`: as configured, and with the loops' EnKF noise drawn anew (their PLANT streams, hence
the plant samples, unchanged: `simulation.path_generators` is redirected, for the loops' seed only, from the
ENKF spawn-key slot to another; identification is untouched, so both runs share the offline gain). Then, over
the plants with an offline gain, for six comparisons (a against b, on the same plant samples):

- offline against itself and online against itself ("anew": the noise drawn anew; both ways round);
- online against offline, as configured and with the noise drawn anew;

how many plants a loses more paths on by the bare counts, and how many the test calls more than chance explains
(p < PAIRED_LEVEL), also among the plants whose offline loop rdsexp calls `stable`; then the plants where any
comparison loses more. docs/online.md shows its table for seeds 0-9 (about 30 minutes on two cores).

    python experiments/paired_null.py [--seeds 0-9] [--n 30] [--paths 100] [--jobs 2] [--out CSV] [--override K=V ...]

--override adds a config override to every run (repeatable), e.g. closed_loop.horizon=300: online's losses on some
plants come after the default 100 steps (docs/online.md, "Over a longer horizon").
"""
from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import json
import multiprocessing
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from coverage import experiment  # noqa: E402  (the validated Experiment of a plant file)
from random_plants import draw_plants, write_plant  # noqa: E402

from rdsexp.numerics.verdict import PAIRED_LEVEL, paired_losses  # noqa: E402

LOOPS_KEY = (1,)      # pipeline.SPAWN_KEYS["closed_loop"] (the online loop's too): the seed whose EnKF noise is redrawn
ANEW = 7              # the spawn-key slot the redrawn noise comes from (simulation.PLANT = 0, ENKF = 1)
COMPARISONS = {"offline anew vs offline": ("off_anew", "off"), "offline vs offline anew": ("off", "off_anew"),
               "online anew vs online": ("on_anew", "on"), "online vs online anew": ("on", "on_anew"),
               "online vs offline": ("on", "off"), "online anew vs offline anew": ("on_anew", "off_anew")}


@contextlib.contextmanager
def noise_drawn_anew():
    """Within it, the loops' EnKF noise comes from another spawn-key slot (ANEW); their plant samples, and every
    stream of identification, are those of the run as configured."""
    import rdsexp.numerics.simulation as simulation
    draw = simulation.path_generators

    def redirected(seed, purpose, which):
        root = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        loops = purpose == simulation.ENKF and tuple(root.spawn_key[:1]) == LOOPS_KEY
        return draw(seed, ANEW if loops else purpose, which)

    simulation.path_generators = redirected
    try:
        yield
    finally:
        simulation.path_generators = draw


def run_overrides(paths: int, overrides=()) -> list[str]:
    """The overrides of every run: controller=online, `paths` paths, no open loop, no recording, then `overrides`."""
    return ["controller=online", f"closed_loop.paths={paths}", "closed_loop.open_loop=false", "tracking=off",
            *overrides]


def lost_paths(config_dir: Path, plant: str, paths: int, anew: bool, overrides=()) -> dict:
    """One run of `plant` with controller=online: the paths each loop lost, the offline loop's verdict."""
    from rdsexp.experiment.pipeline import run_experiment
    with noise_drawn_anew() if anew else contextlib.nullcontext():
        tables = run_experiment(experiment(plant, config_dir, run_overrides(paths, overrides))).tables
    ways, metrics = tables["paths"], tables["metrics"].set_index("experiment")
    lost = {loop: sorted(int(p) for p in ways[(ways["experiment"] == loop) & (ways["failed_at"] >= 0)]["path"])
            for loop in ("closed_loop", "online")}
    gain = "closed_loop" in metrics.index and np.isfinite(metrics.loc["online", "offline_rate_plant"])
    return {"off": lost["closed_loop"], "on": lost["online"], "gain": bool(gain),
            "verdict": str(metrics.loc["closed_loop", "verdict"]) if gain else ""}


def one_plant(config_dir: Path, seed: int, plant: str, paths: int, overrides=()) -> dict:
    """Both runs of one plant: its row (lost path lists as JSON)."""
    row = {"seed": seed, "plant": plant}
    try:
        plain, anew = (lost_paths(config_dir, plant, paths, a, overrides) for a in (False, True))
    except Exception as err:                    # noqa: BLE001 -- a failed run is a row, not the end of the table
        return row | {"error": f"{type(err).__name__}: {err}"[:300]}
    return row | {"gain": plain["gain"], "verdict": plain["verdict"], "off": json.dumps(plain["off"]),
                  "on": json.dumps(plain["on"]), "off_anew": json.dumps(anew["off"]), "on_anew": json.dumps(anew["on"])}


def tally(table: pd.DataFrame, paths: int) -> list[str]:
    """The comparisons' counts over the plants with an offline gain (see the module docstring)."""
    rows = table[table.get("gain", pd.Series(False, index=table.index)).fillna(False).astype(bool)]
    stable = (rows["verdict"] == "stable").to_numpy()
    lost = {col: [np.isin(np.arange(paths), json.loads(v)) for v in rows[col]]
            for col in ("off", "on", "off_anew", "on_anew")}
    lines = [f"{len(rows)} plants with an offline gain, {int(stable.sum())} with an offline loop called stable; per "
             f"comparison a vs b: plants where a loses more by the bare counts and by the paired test (p < "
             f"{PAIRED_LEVEL}), in brackets those where the offline loop is stable"]
    flagged = np.zeros(len(rows), bool)
    for name, (a, b) in COMPARISONS.items():
        more = np.array([x.sum() > y.sum() for x, y in zip(lost[a], lost[b])])
        beyond = np.array([paired_losses(x, y)[2] < PAIRED_LEVEL for x, y in zip(lost[a], lost[b])])
        flagged |= more
        lines.append(f"  {name:28s} bare {int(more.sum()):3d} ({int((more & stable).sum())})   test "
                     f"{int(beyond.sum()):3d} ({int((beyond & stable).sum())})")
    for i in np.flatnonzero(flagged):
        r = rows.iloc[i]
        tests = [paired_losses(lost[a][i], lost[b][i]) for a, b in (COMPARISONS["online vs offline"],
                                                                   COMPARISONS["online anew vs offline anew"])]
        lines.append(f"  seed {r.seed} {r.plant} ({r.verdict}): lost offline {lost['off'][i].sum()} / "
                     f"{lost['off_anew'][i].sum()} anew, online {lost['on'][i].sum()} / {lost['on_anew'][i].sum()} "
                     "anew; online vs offline alone " + ", ".join(f"{a} vs {b} (p = {p:.3g})" for a, b, p in tests))
    return lines


def seeds_of(text: str) -> list[int]:
    """'0-9' or '0,3,5' (or a mix) as a list of seeds; argparse's one-line error otherwise."""
    out = []
    for part in filter(None, text.split(",")):
        low, _, high = part.partition("-")
        if not (low.isdigit() and (high.isdigit() or not high)):
            raise argparse.ArgumentTypeError(f"{text!r}: expected seeds as 0-9 or 0,3,5")
        out += list(range(int(low), int(high or low) + 1))
    if not out:
        raise argparse.ArgumentTypeError(f"{text!r}: no seed")
    return out


def positive(text: str) -> int:
    """An integer >= 1, else argparse's one-line error."""
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected an integer >= 1")
    return int(text)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=seeds_of, default="0-9", help="draws of random_plants.py (default 0-9)")
    parser.add_argument("--n", type=positive, default=30, help="plants per draw (default 30)")
    parser.add_argument("--paths", type=positive, default=100, help="closed_loop.paths (default 100)")
    parser.add_argument("--jobs", type=positive, default=2, help="plants at a time (default 2)")
    parser.add_argument("--out", type=Path, help="CSV of the per-plant table")
    parser.add_argument("--override", action="append", default=[], metavar="KEY=VALUE",
                        help="extra config override for every run (repeatable)")
    args = parser.parse_args(argv)
    rows = []
    # spawned workers: the draw runs designs (BLAS threads) in this process, which a forked worker can deadlock on
    spawn = multiprocessing.get_context("spawn")
    with tempfile.TemporaryDirectory() as tmp, concurrent.futures.ProcessPoolExecutor(args.jobs, mp_context=spawn) \
            as pool:
        futures = []
        for seed in args.seeds:
            config_dir = Path(tmp) / f"draw{seed}"
            for plant in draw_plants(args.n, seed):
                write_plant(plant, config_dir, f"experiments/random_plants.py --seed {seed}")
                if not futures:         # the overrides checked on the first plant, before any run
                    try:
                        experiment(plant.name, config_dir, run_overrides(args.paths, args.override))
                    except Exception as err:     # noqa: BLE001 -- Hydra's and the config's errors alike
                        parser.error(f"--override: {str(err).strip().splitlines()[0]}")
                futures.append(pool.submit(one_plant, config_dir, seed, plant.name, args.paths, args.override))
        for done in concurrent.futures.as_completed(futures):
            rows.append(done.result())
            print(f"\r{len(rows)}/{len(futures)} plants", end="", flush=True)
    print()
    table = pd.DataFrame(rows).sort_values(["seed", "plant"], key=lambda c: c.map(
        lambda v: int(v[2:]) if isinstance(v, str) and v.startswith("rp") else v))
    if "error" in table:
        for r in table[table["error"].notna()].itertuples():
            print(f"seed {r.seed} {r.plant}: {r.error}")
    print("\n".join(tally(table, args.paths)))
    if args.out:
        table.to_csv(args.out, index=False)
        print(f"table: {args.out}")
    return table


if __name__ == "__main__":
    main()
