"""Random plants through the command line: how often does the default experiment end stable?

Draws N random plant files from one seed and runs each through `python -m rdsexp` with the default
configuration (identification, modeling, the default design's gain from the identified moments, the
closed-loop Monte Carlo), then reads every run's record from the store and prints one row per plant:

- the draw: n, m, ny, p, the family of xi, the exact open-loop mean-square rate (F = 0) on the true
  plant and the optimal rate (the `proposed` design on the family's exact moments, true plant);
- the run: completed (run status `complete`), modeled (a modeling_status with moments, `results.MODELED`), the
  selected gain's exact rate on the true plant (rate_plant), the closed loop's verdict (stable / unstable /
  undetermined / failed; "-" where the record has none), its empirical rate and interval [low, high],
  and the fraction of failed paths; y_rate: the exact rate of the same gain fed by the best linear
  observer of y found on the true plant (`observer_loop.best_observer`; "-" when the outputs depend on
  xi or u): a loop through the outputs with this gain can decay only if some observer makes it < 1;
- totals: completed, modeled, stable with no failed path (over all plants, and over the plants whose
  y_rate is below 1 or not computed), and the contradictions: loops whose verdict is unstable /
  undetermined / failed although the selected gain is mean-square stabilizing on the true plant
  (rate_plant < 1).

The draw (plant i depends on the seed and i only: plant i is drawn from child i of one numpy
Generator seeded by --seed): n in 2..6, m in 1..2, ny in 1..n, p in 1..3, the family cycling through
normal, uniform, bernoulli, discrete (and `independent`, a bernoulli block beside a uniform or normal
block, when the installed rdsexp knows that family). xi means are O(1) (a discrete xi is redrawn
until every component has std >= 0.05); every xi_j enters A or B (sometimes C) through a random
basis matrix of modest norm, scaled so that std(xi_j) ||M_j|| is 10-45% of the norm of the mean
matrix M(E xi); a bernoulli xi_j is sometimes a packet dropout (B_j = B(E xi) / E[xi_j], so that
B_0 = 0 when no other xi_k enters B). The A bases are scaled together so that the exact open-loop
rate hits a drawn target: with probability 1/2 in [1.03, 1.30] (open-loop mean-square unstable),
else in [0.70, 0.97].
A draw is rejected and redrawn when the mean system (A, B, C at E[xi]) is not controllable or not
observable (PBH test with a relative margin 1e-3), or when the `proposed` design on the exact moments
gives no gain with exact rate below 0.95 on the true plant (every plant is mean-square stabilizable
with a margin). Each plant file (DIR/plant/rp<i>.yaml, `name: rp<i>`) is run as

    python -m rdsexp --config-dir DIR plant=rp<i> closed_loop.paths=auto store=STORE [overrides]

--jobs at a time, each with a timeout, its output in a log file per plant, LOGS/rp<i>.log with LOGS =
STORE/random_plants_logs (beside --out). A plant whose run does not end stable with no failed path
is copied to LOGS/plant/rp<i>.yaml (`python -m rdsexp --config-dir LOGS plant=rp<i>` reruns it).
The table is also written as CSV (--out, default STORE/random_plants.csv), with each run's
directory, code version (the runs of one table should share it) and the reason of a failure.

    python experiments/random_plants.py [--n 50] [--seed 0] [--paths auto] [--jobs 2] [--timeout 600]
        [--store /tmp/random_plants/store-SEED] [--out CSV] [--keep-plants DIR]
        [--override KEY=VALUE ...] [--only-draw] [--guess-off SD]

--guess-off SD (default 1) gives every run a prior guess of xi (identification.xi_guess, which the EnKF starts
from and the identification and online gains are designed on) SD standard deviations of each component off the
plant file's mean (`wrong_guess`): a researcher's knowledge of the plant, not its law (a run is blind); 0 leaves
the default, xi = 0.
"""
from __future__ import annotations

import argparse
import concurrent.futures
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from rdsexp import runs
from rdsexp.errors import DamagedRecord
from rdsexp.experiment.pipeline.results import MODELED
from rdsexp.experiment.store import RunStore, layout
from rdsexp.numerics.analysis import ms_rate
from rdsexp.numerics.distributions import from_spec
from rdsexp.numerics.observer_loop import applies, best_observer
from rdsexp.numerics.synthesis import synthesize
from rdsexp.numerics.systems import AffineRandomSystem
from rdsexp.numerics.verdict import PAIRED_LEVEL

REPO = Path(__file__).resolve().parents[1]
BASE_FAMILIES = ("normal", "uniform", "bernoulli", "discrete")
UNSTABLE_TARGET = (1.03, 1.30)       # exact open-loop rate of an open-loop unstable plant
STABLE_TARGET = (0.70, 0.97)         # ... of an open-loop stable plant
DESIGN_MARGIN = 0.95                 # the proposed design on the exact moments must reach this rate
PBH_MARGIN = 1e-3                    # sigma_min([lambda I - A, B]) / max(1, ||A||) above this
RANDOM_SHARE = (0.10, 0.45)          # std(xi_j) ||M_j|| / ||M(E xi)||
MIN_STD = 0.05                       # a discrete xi_j whose std is below this is redrawn
DIGITS = 6                           # significant digits of the numbers in a plant file
MAX_ATTEMPTS = 500
BAD_VERDICTS = ("unstable", "undetermined", "failed")


def independent_available() -> bool:
    """Whether this rdsexp parses the family `independent` (being added; skipped when absent)."""
    try:
        from_spec({"family": "independent", "components": [{"family": "bernoulli", "prob": [0.8]},
                                                            {"family": "uniform", "low": [0.0], "high": [1.0]}]})
        return True
    except Exception:                  # unknown family (ValueError) or anything a half-made family raises
        return False


# ---------------------------------------------------------------------------------------- the draw
def _round(x):
    """Nested lists of floats with DIGITS significant digits (what the plant file holds)."""
    arr = np.asarray(x, dtype=float)
    if arr.ndim == 0:
        return float(f"{float(arr):.{DIGITS}g}") + 0.0           # + 0.0: no -0.0 in the file
    return [_round(v) for v in arr]


def _xi_spec(rng: np.random.Generator, family: str, p: int) -> dict:
    """A family spec {family: ..., parameters} of dimension p with O(1) means."""
    if family == "normal":
        mean = rng.uniform(-1.2, 1.2, p)
        std = rng.uniform(0.1, 0.4, p)
        G = rng.standard_normal((p, p))
        S = G @ G.T + p * np.eye(p)                             # a mild random correlation
        corr = S / np.sqrt(np.outer(np.diag(S), np.diag(S)))
        return {"family": "normal", "mean": _round(mean), "cov": _round(corr * np.outer(std, std))}
    if family == "uniform":
        center, half = rng.uniform(-1.0, 1.2, p), rng.uniform(0.1, 0.6, p)
        return {"family": "uniform", "low": _round(center - half), "high": _round(center + half)}
    if family == "bernoulli":
        return {"family": "bernoulli", "prob": _round(rng.uniform(0.6, 0.95, p))}
    if family == "discrete":
        while True:                     # redrawn until every xi_j varies (std >= MIN_STD): not a constant
            count = int(rng.integers(2, 5))
            values = rng.uniform(-1.0, 1.2, p) + rng.uniform(0.1, 0.5, p) * rng.standard_normal((count, p))
            probs = np.array(_round(rng.dirichlet(2 * np.ones(count))))
            probs[-1] = round(1.0 - probs[:-1].sum(), 10)       # sums to 1 after rounding
            spec = {"family": "discrete", "values": _round(values), "probs": [float(v) for v in probs]}
            if np.sqrt(np.diag(from_spec(spec).cov)).min() >= MIN_STD:
                return spec
    if family == "independent":                                 # a bernoulli block beside a uniform/normal one
        blocks = [{"family": "bernoulli", "prob": _round(rng.uniform(0.6, 0.95, 1))},
                  _xi_spec(rng, str(rng.choice(["uniform", "normal"])), p - 1)]
        if rng.random() < 0.5:
            blocks.reverse()
        return {"family": "independent", "components": blocks}
    raise ValueError(f"family {family!r}")


def _bernoulli_components(spec: dict) -> list[int]:
    """The indices j of xi that are 0/1 (bernoulli, or a bernoulli block of `independent`)."""
    if spec["family"] == "bernoulli":
        return list(range(len(spec["prob"])))
    if spec["family"] == "independent":
        out, start = [], 0
        for block in spec["components"]:
            size = len(from_spec(block).mean)
            if block["family"] == "bernoulli":
                out += list(range(start, start + size))
            start += size
        return out
    return []


def _basis_matrix(rng: np.random.Generator, rows: int, cols: int) -> np.ndarray:
    """A random matrix of unit spectral norm, sometimes sparse (at least one nonzero entry)."""
    M = rng.standard_normal((rows, cols))
    if rng.random() < 0.5:
        mask = rng.random((rows, cols)) < rng.uniform(0.15, 0.8)
        mask.flat[rng.integers(rows * cols)] = True
        M = M * mask
    return M / np.linalg.norm(M, 2)


def _pbh(A: np.ndarray, M: np.ndarray) -> float:
    """Smallest sigma_min([lambda I - A, M]) over the eigenvalues lambda of A, relative to
    max(1, ||A||): 0 when (A, M) is not controllable ((A^T, C^T): (A, C) not observable)."""
    n = A.shape[0]
    scale = max(1.0, np.linalg.norm(A, 2))
    return float(min(np.linalg.svd(np.hstack([lam * np.eye(n) - A, M]), compute_uv=False)[-1]
                     for lam in np.linalg.eigvals(A)) / scale)


@dataclass
class Plant:
    """A drawn plant: its file content and what the draw computed on the true plant."""

    name: str
    index: int
    n: int
    m: int
    ny: int
    p: int
    family: str
    unstable_target: bool
    target: float
    open_loop_rate: float
    mean_rho: float                      # spectral radius of A(E xi): the rate without the randomness
    optimal_rate: float                  # proposed design on the exact moments, exact rate on the plant
    attempts: int
    rejected: dict = field(default_factory=dict)
    content: dict = field(default_factory=dict)


def system_of(content: dict) -> tuple[AffineRandomSystem, object]:
    """(AffineRandomSystem with its xi_dist, the family) from a plant file's content."""
    dist = from_spec(content["xi"])
    return AffineRandomSystem(content["A"], content["B"], content.get("C"), content.get("D"), xi_dist=dist), dist


def _draw_once(rng: np.random.Generator, family: str, unstable: bool) -> tuple[dict, float, dict]:
    """One candidate plant file content on the given side (open-loop unstable or stable), its target
    rate and the sizes."""
    n, m = int(rng.integers(2, 7)), int(rng.integers(1, 3))
    ny, p = int(rng.integers(1, n + 1)), int(rng.integers(1, 4))
    if family == "independent":
        p = max(p, 2)                                           # two blocks at least
    target = float(rng.uniform(*(UNSTABLE_TARGET if unstable else STABLE_TARGET)))
    spec = _xi_spec(rng, family, p)
    dist = from_spec(spec)
    mean, std = dist.mean, np.sqrt(np.diag(dist.cov))
    weight = 1.0 / np.maximum(std, 0.2)                         # ||M_j|| = share ||Mbar|| / std_j (capped)
    bern = _bernoulli_components(spec)

    Abar = rng.standard_normal((n, n))
    Abar /= max(np.abs(np.linalg.eigvals(Abar)).max(), 1e-3)
    Bbar = rng.standard_normal((n, m))
    Bbar /= np.linalg.norm(Bbar, axis=0)
    if rng.random() < 0.5:                                      # measured states, or random outputs
        Cbar = np.eye(n)[np.sort(rng.choice(n, ny, replace=False))]
    else:
        Cbar = rng.standard_normal((ny, n))
        Cbar /= np.linalg.norm(Cbar, axis=1, keepdims=True)
    C_random = rng.random() < 0.2

    A, B, C = np.zeros((p, n, n)), np.zeros((p, n, m)), np.zeros((p, ny, n))
    dropout = bern[0] if bern and rng.random() < 0.5 else None
    for j in range(p):
        if j == dropout:
            B[j] = Bbar / mean[j]                               # with B_0 the rest: B(xi) = xi_j Bbar / E[xi_j]
        elif rng.random() < 0.4:
            B[j] = rng.uniform(*RANDOM_SHARE) * weight[j] * np.linalg.norm(Bbar, 2) * _basis_matrix(rng, n, m)
        if rng.random() < 0.75 or not B[j].any():               # every xi_j enters somewhere
            A[j] = rng.uniform(*RANDOM_SHARE) * weight[j] * np.linalg.norm(Abar, 2) * _basis_matrix(rng, n, n)
        if C_random and rng.random() < 0.5:
            C[j] = 0.5 * rng.uniform(*RANDOM_SHARE) * weight[j] * _basis_matrix(rng, ny, n)
    A0 = Abar - np.tensordot(mean, A, axes=1)                  # A(E xi) = Abar, same for B, C
    B0 = Bbar - np.tensordot(mean, B, axes=1)
    C0 = Cbar - np.tensordot(mean, C, axes=1)
    A_all = np.concatenate([A0[None], A])
    plant = AffineRandomSystem(A_all, np.concatenate([B0[None], B]), xi_dist=dist)
    A_all *= target / ms_rate(plant, dist, np.zeros((m, n)))   # the rate is homogeneous in the A bases
    content = {
        "A": _round(A_all),
        "B": _round(np.concatenate([B0[None], B])),
        "C": _round(np.concatenate([C0[None], C]) if C.any() else C0[None]),
        "D": None,
        "xi": spec,
    }
    return content, target, {"n": n, "m": m, "ny": ny, "p": p}


def draw_plant(rng: np.random.Generator, index: int, family: str) -> Plant:
    """Plant `rp<index>`: draws until the checks pass (see the module docstring)."""
    rejected: dict[str, int] = {}
    unstable = bool(rng.random() < 0.5)          # once per plant: a rejection redraws on the same side
    for attempt in range(1, MAX_ATTEMPTS + 1):
        content, target, sizes = _draw_once(rng, family, unstable)
        system, dist = system_of(content)                       # from the rounded file content
        rate0 = ms_rate(system, dist, np.zeros((system.m, system.n)))
        Am, Bm, Cm, _ = system.at(dist.mean)
        reason = None
        if (rate0 >= 1) != unstable:
            reason = "wrong side after rounding"
        elif _pbh(Am, Bm) < PBH_MARGIN:
            reason = "mean system not controllable"
        elif _pbh(Am.T, Cm.T) < PBH_MARGIN:
            reason = "mean system not observable"
        else:
            res = synthesize(system, system.check_distribution(dist), "proposed")   # the exact moments
            optimal = ms_rate(system, dist, res.F) if res.F is not None else math.inf
            if not optimal < DESIGN_MARGIN:
                reason = f"not stabilizable below {DESIGN_MARGIN}"
        if reason:
            rejected[reason] = rejected.get(reason, 0) + 1
            continue
        name = f"rp{index}"
        return Plant(name, index, family=family, unstable_target=unstable, target=target, open_loop_rate=rate0,
                     mean_rho=float(np.abs(np.linalg.eigvals(Am)).max()), optimal_rate=optimal, attempts=attempt,
                     rejected=rejected, content={"name": name, **content}, **sizes)
    raise RuntimeError(f"rp{index}: no acceptable {family} plant in {MAX_ATTEMPTS} draws ({rejected})")


def draw_plants(n: int, seed: int) -> list[Plant]:
    """Plants rp0..rp<n-1>; plant i is drawn from child i of the Generator seeded by `seed`."""
    families = BASE_FAMILIES + (("independent",) if independent_available() else ())
    children = np.random.default_rng(seed).spawn(n)
    return [draw_plant(children[i], i, families[i % len(families)]) for i in range(n)]


def write_plant(plant: Plant, config_dir: Path, header: str) -> Path:
    """DIR/plant/<name>.yaml, with a comment header saying how it was drawn."""
    path = config_dir / "plant" / f"{plant.name}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    comment = (f"# {header}\n# family {plant.family}, n {plant.n} m {plant.m} ny {plant.ny} p {plant.p}; "
               f"exact open-loop rate {plant.open_loop_rate:.4f} (target {plant.target:.4f}), optimal rate "
               f"(proposed, exact moments) {plant.optimal_rate:.4f}; accepted at draw {plant.attempts}\n")
    path.write_text(comment + yaml.safe_dump(plant.content, default_flow_style=None, sort_keys=False, width=100))
    with open(path) as f:                                       # the file is what was checked
        again = yaml.safe_load(f)
    system, dist = system_of(again)
    if abs(ms_rate(system, dist, np.zeros((system.m, system.n))) - plant.open_loop_rate) > 1e-12:
        raise RuntimeError(f"{path}: the written plant differs from the drawn one")
    return path


# ------------------------------------------------------------------------------------------ running
@dataclass
class Outcome:
    plant: str
    returncode: int | None
    seconds: float
    log: Path
    run_dir: Path | None
    note: str = ""


def wrong_guess(plant: Plant, seed: int, sds: float) -> np.ndarray:
    """(p,): an identification.xi_guess `sds` standard deviations of each component of xi off the plant file's
    mean, the sign alternating over the components (+ on the first where seed + the plant's index is even, - where
    odd), kept 0.02 inside a bounded support: a prior guess wrong by a known amount (--guess-off)."""
    _, dist = system_of(plant.content)
    mean, sd = np.asarray(dist.mean, float), np.sqrt(np.diag(np.asarray(dist.cov, float)))
    sign = np.where(np.arange(mean.size) % 2 == 0, 1.0, -1.0) * (1.0 if (seed + plant.index) % 2 == 0 else -1.0)
    low, high = (np.asarray(b, float) for b in getattr(dist, "support", (-np.inf, np.inf)))
    return np.clip(mean + sds * sign * sd, low + 0.02, high - 0.02)


def _overrides(args, plant: str) -> list[str]:
    """The command line's overrides; the user's --override replaces a default of the same key."""
    items = {"plant": plant, "closed_loop.paths": str(args.paths), "store": str(args.store)}
    if plant in getattr(args, "guesses", {}):                   # --guess-off
        items["identification.xi_guess"] = "[" + ",".join(f"{v:.5g}" for v in args.guesses[plant]) + "]"
    for text in args.override:
        key, sep, value = text.partition("=")
        if not sep:
            raise SystemExit(f"--override {text!r}: expected KEY=VALUE")
        items.pop(key.lstrip("+~"), None)
        items[key] = value
    return [f"{k}={v}" for k, v in items.items()]


def _find_run_dir(output: str, store: Path, plant: str, before: set[Path]) -> Path | None:
    """The run directory the command line printed, else the one new run of this plant in the store."""
    found = re.findall(r"^\s*run directory: (.+)$", output, flags=re.M)
    if found and layout.is_run(Path(found[-1].strip())):
        return Path(found[-1].strip())
    stored = RunStore(store / "runs").runs(warn=False) if (store / "runs").is_dir() else []
    new = [run.dir for run in stored if run.dir not in before and f"plant={plant}" in run.record.overrides]
    return sorted(new)[-1] if new else None


def run_plant(args, config_dir: Path, plant: str, log_dir: Path) -> Outcome:
    """One plant through the command line, its output into log_dir/<plant>.log."""
    cmd = [sys.executable, "-m", "rdsexp", "--config-dir", str(config_dir), *_overrides(args, plant)]
    log = log_dir / f"{plant}.log"
    runs_dir = args.store / "runs"
    before = {p for p in runs_dir.iterdir() if layout.is_run(p)} if runs_dir.is_dir() else set()
    start = time.perf_counter()
    note = ""
    with open(log, "w") as f:
        f.write("$ " + " ".join(cmd) + "\n")
        f.flush()
        proc = subprocess.Popen(cmd, cwd=REPO, stdout=f, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            code = proc.wait(timeout=args.timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)             # the run and its workers (its own session)
            proc.wait()
            code, note = None, f"timeout after {args.timeout:g} s"
    seconds = time.perf_counter() - start
    output = log.read_text(errors="replace")
    if "Traceback" in output:
        note = "; ".join(filter(None, [note, "traceback in log: " + _last_error(output)]))
    elif code not in (0, None):
        note = "; ".join(filter(None, [note, f"exit {code}: " + _last_error(output)]))
    return Outcome(plant, code, seconds, log, _find_run_dir(output, args.store, plant, before), note)


def _last_error(output: str) -> str:
    """The last non-empty line of a log (the exception or the one-line error); when that line points
    above (Hydra's config errors), the first line of the output too."""
    lines = [line.strip() for line in output.splitlines()[1:] if line.strip()]     # [0]: the command
    if not lines:
        return ""
    text = f"{lines[0]} ... {lines[-1]}" if "above" in lines[-1] and len(lines) > 1 else lines[-1]
    return text[:300]


def read_record(outcome: Outcome) -> dict:
    """What the table shows from a run's record and metrics table (missing keys stay None)."""
    row = {"run_status": None, "modeling_status": None, "synthesis_status": None, "rate_plant": None,
           "verdict": None, "verdict_reason": None, "closed_loop_status": None, "cl_rate": None, "cl_low": None,
           "cl_high": None, "cl_paths": None, "failed_fraction": None, "run_seconds": None, "code_version": None,
           "online_failed_fraction": None, "online_final_rate": None, "offline_rate_plant": None,
           "lost_online_only": None, "lost_offline_only": None, "lost_more_p": None, "lost_held_unstable": None,
           "cost_ratio_plant": None, "rate_excess_plant": None}
    if outcome.run_dir is None:
        return row
    try:
        stored = runs.open_run(outcome.run_dir)
    except (OSError, LookupError, DamagedRecord) as err:
        outcome.note = "; ".join(filter(None, [outcome.note, f"run.json unreadable: {err}"]))
        return row
    record, summary = stored.record, stored.record.summary
    row.update(run_status=record.status, run_seconds=record.seconds, code_version=record.code_version,
               modeling_status=summary.modeling_status, synthesis_status=summary.synthesis_status,
               rate_plant=_value(summary.rate_plant), verdict=summary.verdict(),
               verdict_reason=summary.verdict_reason(), closed_loop_status=summary.status(),
               # the end-to-end figure: the loop's gain against the optimum for the plant's law
               **{name: _value(record.metric(name)) for name in ("cost_ratio_plant", "rate_excess_plant")})
    if summary.status() is not None:            # the loop ran: its rate (NaNs where no window measured it)
        row.update(zip(("cl_rate", "cl_low", "cl_high"), map(_value, summary.rate())))
        row["failed_fraction"] = summary.failed_fraction()
    if "metrics" in record.tables:
        try:
            metrics = stored.table("metrics")
            loop = metrics[metrics["experiment"] == "closed_loop"]
            if len(loop):
                loop = loop.iloc[0]
                for key, column in (("verdict", "verdict"), ("verdict_reason", "verdict_reason"),
                                    ("failed_fraction", "failed_fraction"),
                                    ("cl_rate", "rate"), ("cl_low", "rate_low"), ("cl_high", "rate_high"),
                                    ("cl_paths", "paths"), ("closed_loop_status", "status")):
                    if row[key] is None and column in loop.index and not _missing(loop[column]):
                        row[key] = loop[column].item() if hasattr(loop[column], "item") else loop[column]
            online = metrics[metrics["experiment"] == "online"]       # controller=online: its row
            if len(online):
                online = online.iloc[0]
                row.update(online_failed_fraction=float(online["failed_fraction"]),
                           online_final_rate=float(online["final_rate_plant_median"]),
                           offline_rate_plant=float(online["offline_rate_plant"]),
                           **{key: float(online[key]) for key in ("lost_online_only", "lost_offline_only",
                                                                  "lost_more_p", "lost_held_unstable")
                              if key in online.index})
        except Exception as err:                                # a damaged table is a finding, not a crash
            outcome.note = "; ".join(filter(None, [outcome.note, f"metrics unreadable: {type(err).__name__}: {err}"]))
    return row


def _missing(value) -> bool:
    return value is None or (isinstance(value, float) and math.isnan(value))


def _value(number: float) -> float | None:
    """A record's number as the table shows it: None where the record has none (NaN)."""
    return None if _missing(number) else number


# ------------------------------------------------------------------------------------------ output
def _f(value, fmt: str = ".4f") -> str:
    return "-" if _missing(value) else format(value, fmt)


def draw_table(plants: list[Plant]) -> pd.DataFrame:
    return pd.DataFrame([{
        "plant": p.name, "n": p.n, "m": p.m, "ny": p.ny, "p": p.p, "family": p.family,
        "target": round(p.target, 4), "open_loop_rate": p.open_loop_rate,
        "mean_rho": p.mean_rho, "optimal_rate": p.optimal_rate,
        "attempts": p.attempts, "rejected": ", ".join(f"{k} {v}" for k, v in p.rejected.items())}
        for p in plants])


def print_draw(plants: list[Plant], seconds: float, config_dir: Path, kept: bool) -> None:
    table = draw_table(plants)
    shown = table.drop(columns="target").assign(**{c: table[c].map(_f) for c in ("open_loop_rate", "mean_rho",
                                                                                   "optimal_rate")})
    print(shown.to_string(index=False))
    unstable = int((table["open_loop_rate"] >= 1).sum())
    families = {k: int(v) for k, v in table["family"].value_counts().items()}
    print(f"\n{len(plants)} plants in {seconds:.1f} s: open-loop mean-square unstable {unstable}/{len(plants)} "
          f"({unstable / max(len(plants), 1):.0%}); families {families}; "
          f"{int(table['attempts'].sum()) - len(plants)} draws rejected")
    print(f"plant files: {config_dir / 'plant'}" + ("" if kept else " (temporary: --keep-plants DIR keeps them)"))


def results_table(plants: list[Plant], outcomes: dict[str, Outcome]) -> pd.DataFrame:
    rows = []
    for p in plants:
        o = outcomes[p.name]
        rec = read_record(o)
        rows.append({"plant": p.name, "n": p.n, "m": p.m, "ny": p.ny, "p": p.p, "family": p.family,
                     "open_loop_rate": p.open_loop_rate, "mean_rho": p.mean_rho,
                     "optimal_rate": p.optimal_rate, "completed": rec["run_status"] == "complete",
                     "modeled": rec["modeling_status"] in MODELED,
                     **rec, "wall_seconds": round(o.seconds, 1), "returncode": o.returncode,
                     "run_dir": str(o.run_dir) if o.run_dir else None, "log": str(o.log), "note": o.note,
                     "y_rate": through_outputs(p, o.run_dir)})
        rows[-1]["why"] = _why(rows[-1])
    return pd.DataFrame(rows)


def through_outputs(plant: Plant, run_dir: Path | None) -> float | None:
    """The exact rate of the run's selected gain fed by the best linear observer of y found on the true
    plant (`observer_loop.best_observer`, the run's estimate x_{k|k} or x_{k|k-1}): below 1, a loop through
    the outputs with this gain can decay; None when there is no gain or the outputs depend on xi or u."""
    system, _ = system_of(plant.content)
    if run_dir is None or applies(system):
        return None
    try:
        stored = runs.open_run(run_dir)
        gains = stored.table("gains")
        selected = gains[gains["selected"]]
        estimate = stored.record.summary.fed_back
    except Exception:                                    # a damaged record or no gains: no number, not a crash
        return None
    if not len(selected):
        return None
    F = np.array([[selected.iloc[0][f"F[{i},{j}]"] for j in range(plant.n)] for i in range(plant.m)])
    if not np.all(np.isfinite(F)):
        return None
    return best_observer(system, None, F, estimate=estimate).rate


def _why(row: dict) -> str:
    """One line on what went wrong: the runner's note, the modeling failure or the verdict's reason."""
    parts = [row["note"]]
    if row["run_dir"] is None:
        parts.append("no run directory found")
    elif row["run_status"] != "complete":
        parts.append(f"run {row['run_status']}")
    if not row["modeled"] and row["modeling_status"]:
        parts.append(f"modeling: {row['modeling_status']}")
    elif row["modeled"] and not (row["verdict"] or row["closed_loop_status"]):     # no gain, so no loop
        parts.append(f"no closed loop: the design on the identified model ended {row['synthesis_status']}")
    elif row["modeled"] and row["verdict"] != "stable":
        parts.append(f"closed loop {row['verdict'] or row['closed_loop_status']}: {row['verdict_reason'] or ''}")
    return "; ".join(p for p in parts if p)


def _clean(r) -> bool:
    """A run that completed, was modeled and ended in a stable loop with no failed path, no note."""
    return bool(r.completed and r.modeled and r.verdict == "stable" and r.failed_fraction == 0 and not r.note)


def end_to_end(r) -> str:
    """The loop's gain against the optimum for the plant's law: an LQ design's cost ratio (x), a rate design's rate
    excess (+); - where the run has neither."""
    if not _missing(r.cost_ratio_plant):
        return f"x{r.cost_ratio_plant:.3f}"
    return "-" if _missing(r.rate_excess_plant) else f"+{r.rate_excess_plant:.4f}"


def print_results(table: pd.DataFrame) -> None:
    def interval(r):
        return "-" if _missing(r.cl_low) else f"[{r.cl_low:.4f}, {r.cl_high:.4f}]"
    shown = pd.DataFrame({
        "plant": table["plant"],
        "n m ny p": [f"{r.n} {r.m} {r.ny} {r.p}" for r in table.itertuples()],
        "family": table["family"],
        "ol_rate": table["open_loop_rate"].map(_f),
        "completed": table["completed"].map(lambda v: "yes" if v else "no"),
        "modeled": table["modeled"].map(lambda v: "yes" if v else "no"),
        "rate_plant": table["rate_plant"].map(_f),
        "verdict": table["verdict"].map(lambda v: "-" if _missing(v) else v),
        "cl_rate": table["cl_rate"].map(_f),
        "interval": [interval(r) for r in table.itertuples()],
        "failed": table["failed_fraction"].map(lambda v: _f(v, ".2f")),
        "paths": table["cl_paths"].map(lambda v: _f(v, ".0f")),
        "y_rate": table["y_rate"].map(_f),
        "e2e": [end_to_end(r) for r in table.itertuples()],
        "s": table["wall_seconds"].map(lambda v: f"{v:.0f}"),
    })
    print(shown.to_string(index=False))
    for r in table.itertuples():
        if not _clean(r):
            print(f"  {r.plant}: {r.why}")
    for name, what, fmt in (("cost_ratio_plant", "LQ cost over the optimum for the plant's law", ".3f"),
                            ("rate_excess_plant", "exact rate above the optimal rate for the plant's law", ".4f")):
        values = pd.to_numeric(table[name], errors="coerce").dropna()
        if len(values):
            print(f"end to end, {what}: median {values.median():{fmt}}, 90th percentile "
                  f"{values.quantile(0.9):{fmt}} ({len(values)} plants)")

    N = len(table)
    completed, modeled = int(table["completed"].sum()), int(table["modeled"].sum())
    has_verdict = table["verdict"].map(lambda v: not _missing(v))
    no_failed = table["failed_fraction"].map(lambda v: not _missing(v) and v == 0)
    if has_verdict.any():
        stable = int(((table["verdict"] == "stable") & no_failed).sum())
        basis = "verdict stable"
        bad = table["verdict"].isin(BAD_VERDICTS) | (table["completed"] & ~has_verdict)
    else:                       # records without verdicts: the interval's upper end decides
        high = table["cl_high"].map(lambda v: np.nan if _missing(v) else v).astype(float)
        stable = int(((high < 1) & no_failed).sum())
        basis = "no verdict recorded: rate interval high < 1"
        bad = ~(high < 1)
    good_gain = table["rate_plant"].map(lambda v: not _missing(v) and v < 1)
    contradictions = table[bad & good_gain]
    print(f"\ncompleted {completed}/{N}, modeled {modeled}/{N}, stable with no failed path {stable}/{N} "
          f"({stable / max(N, 1):.0%}; {basis})")
    looped = table["closed_loop_status"].map(lambda v: not _missing(v))
    decisive = int(table.loc[looped, "verdict"].isin(("stable", "unstable")).sum())
    budget = int(table.loc[looped, "verdict_reason"].map(lambda v: "max_paths" in str(v)).sum())
    paths = pd.to_numeric(table.loc[looped, "cl_paths"], errors="coerce").dropna()
    if len(paths):
        print(f"closed loops decisive (stable or unstable): {decisive}/{int(looped.sum())} "
              f"({decisive / max(int(looped.sum()), 1):.0%}); closed_loop.max_paths reached: {budget}; paths judged "
              f"on: median {paths.median():.0f}, 95th percentile {paths.quantile(0.95):.0f}, max {paths.max():.0f}")
    print(f"contradictions (closed loop not found stable although rate_plant < 1): {len(contradictions)}"
          + (f": {', '.join(contradictions['plant'])}" if len(contradictions) else ""))
    unexplained = [r.plant for r in contradictions.itertuples() if not _explained(r.log)]
    print(f"  of which the run's summary does not say why: {len(unexplained)}"
          + (f": {', '.join(unexplained)}" if unexplained else ""))
    # the loops through y that can decay: a linear observer of y was found that makes the gain's loop decay,
    # or none could be computed (no gain; outputs that depend on xi or u)
    can_decay = table["y_rate"].map(lambda v: _missing(v) or v < 1)
    stable_there = int(((table["verdict"] == "stable") & no_failed & can_decay).sum())
    print(f"among the plants whose gain's loop through y can decay (y_rate < 1, or not computed): stable with no "
          f"failed path {stable_there}/{int(can_decay.sum())} ({stable_there / max(int(can_decay.sum()), 1):.0%}); "
          f"y_rate >= 1: {', '.join(f'{r.plant} ({r.verdict})' for r in table[~can_decay].itertuples()) or 'none'}")
    if table["online_final_rate"].map(lambda v: not _missing(v)).any():
        print_online(table)
    print(f"run wall time: median {table['wall_seconds'].median():.1f} s, max {table['wall_seconds'].max():.1f} s")
    versions = sorted(v for v in table["code_version"].dropna().unique())
    print(f"code version{'s (the runs differ!)' if len(versions) > 1 else ''}: {', '.join(versions) or '-'}")


ONLINE_TOLERANCE = 0.005      # online "no worse": its final gains' median rate at most this above the offline gain's


def print_online(table: pd.DataFrame) -> None:
    """controller=online: per plant, the online loop's final gains' median exact rate on the true plant against
    the offline gain's, and the paths each loop lost; then how often online ends no worse (within
    ONLINE_TOLERANCE, or better) and how often it loses more paths: by the bare counts, and by the exact paired
    test of the paths each loop lost alone (`verdict.paired_losses`, p < PAIRED_LEVEL: more than chance explains),
    also among the plants whose offline loop rdsexp calls `stable` (a plant that loses more paths online beside an
    offline loop it cannot call stable is a different finding from one beside a stable loop), and among those whose
    offline gain's loop through y has no decaying linear observer (y_rate >= 1: there the outputs, not the online
    design, are what no gain of either loop overcomes: on seeds 6 and 17's rp21 every gain, the nominal, the offline
    and each online final one, has a y_rate in [1.048, 1.050] and [1.143, 1.145]; docs/online-rounds.md, a fourteenth
    round). Beside a plant losing more: whether online's lost paths held a gain unstable on the plant before their
    loss (the run's `lost_held_unstable`), or only stable ones, where the loop through the estimate grew."""
    rows = table[table["online_final_rate"].map(lambda v: not _missing(v))
                 | table["online_failed_fraction"].map(lambda v: not _missing(v))]
    gap = rows["online_final_rate"].astype(float) - rows["offline_rate_plant"].astype(float)
    lost_on = rows["online_failed_fraction"].astype(float)
    lost_off = rows["failed_fraction"].map(lambda v: 0.0 if _missing(v) else v).astype(float)
    # columns records of earlier versions lack: NaN
    p, y_rate, held = (rows.get(name, pd.Series(np.nan, index=rows.index)).map(lambda v: np.nan if _missing(v) else v)
                       for name in ("lost_more_p", "y_rate", "lost_held_unstable"))
    print("\nonline (learning-type) against offline, per plant: final gains' median exact rate, the offline gain's, "
          "gap; paths lost (fraction; paths lost by one loop alone, paired test of online losing more)")
    # an offline run with no gain (its identification or design failed) has no closed loop to compare with:
    # counted apart, neither as no worse nor as losing more
    none = rows["offline_rate_plant"].map(_missing).to_numpy()
    for r, g, on, off, gainless, pr, yr, unstable in zip(rows.itertuples(), gap, lost_on, lost_off, none, p, y_rate,
                                                         held):
        alone = "" if not np.isfinite(pr) or r.lost_online_only + r.lost_offline_only == 0 else \
            f" ({r.lost_online_only:.0f} vs {r.lost_offline_only:.0f} alone, p = {pr:.3g})"
        more = "LOST MORE" + (", beyond chance" if pr < PAIRED_LEVEL else ", within chance" if np.isfinite(pr) else "")
        verdict = "  (no offline gain)" if gainless else (
            ("  WORSE" if not g <= ONLINE_TOLERANCE else "")
            + (f"  {more} (offline loop {'-' if _missing(r.verdict) else r.verdict}"
               + (f"; no linear observer holds its gain's loop through y: y_rate {yr:.4f}" if yr >= 1 else "")
               + ("" if not np.isfinite(unstable) else "; online's lost paths held only gains stable on the plant"
                  if unstable == 0 else f"; {unstable:.0f} of online's lost paths held a gain unstable on the plant")
               + ")" if on > off else ""))
        print(f"  {r.plant}: online {_f(r.online_final_rate)} offline {_f(r.offline_rate_plant)} gap "
              f"{'-' if not np.isfinite(g) else format(g, '+.4f')}; lost {on:.2f} vs {off:.2f}{alone}{verdict}")
    compared = ~none
    no_worse = (gap <= ONLINE_TOLERANCE)[compared]
    more = (lost_on > lost_off)[compared]
    beyond = (p < PAIRED_LEVEL)[compared]
    stable = (rows["verdict"] == "stable").to_numpy()[compared]
    unobservable = (y_rate >= 1).to_numpy()[compared]
    print(f"online ends no worse than offline (final median rate <= offline + {ONLINE_TOLERANCE}): "
          f"{int(no_worse.sum())}/{int(compared.sum())} ({no_worse.mean():.0%}); loses more paths: "
          f"{int(more.sum())}/{int(compared.sum())}, {int((more & stable).sum())}/{int(stable.sum())} where the "
          f"offline loop is stable; more than chance explains (paired sign test, p < {PAIRED_LEVEL}): "
          f"{int(beyond.sum())}/{int(compared.sum())}, {int((beyond & stable).sum())}/{int(stable.sum())} where the "
          f"offline loop is stable, {int((beyond & unobservable).sum())}/{int(unobservable.sum())} where no linear "
          f"observer holds the offline gain's loop (y_rate >= 1)"
          + (f"; no offline gain (not compared): {', '.join(rows.plant[none])}" if none.any() else ""))


# what a run's summary (its printed output, in the plant's log) says when the closed loop's verdict
# and the gain's exact rate disagree: the observer's gap, or a window at (or without one above) the floor
EXPLANATIONS = ("the gap is the observer's", "the gap is the outputs'", "the gap is the EnKF's",
                "the window ends at the noise floor", "no window to measure")


def _explained(log) -> bool:
    """Whether the run's printed summary explains a verdict that the gain's exact rate contradicts."""
    try:
        text = Path(log).read_text()
    except (OSError, TypeError):
        return False
    return any(phrase in text for phrase in EXPLANATIONS)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=50, help="number of plants (default 50)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the draw (default 0)")
    parser.add_argument("--paths", type=lambda v: v if v == "auto" else int(v), default="auto",
                        help="closed_loop.paths of every run: a count or auto (default auto, rdsexp's)")
    parser.add_argument("--jobs", type=int, default=2, help="runs at a time (default 2)")
    parser.add_argument("--timeout", type=float, default=600, help="seconds per run (default 600)")
    parser.add_argument("--store", type=Path, help="run store (default /tmp/random_plants/store-SEED)")
    parser.add_argument("--out", type=Path, help="CSV of the table (default STORE/random_plants.csv)")
    parser.add_argument("--keep-plants", type=Path, metavar="DIR",
                        help="write the plant files to DIR/plant/ and keep them (default: a temporary directory)")
    parser.add_argument("--override", action="append", default=[], metavar="KEY=VALUE",
                        help="extra override for every run (repeatable)")
    parser.add_argument("--only-draw", action="store_true", help="draw and write the plants, print them, run nothing")
    parser.add_argument("--guess-off", type=float, default=1.0, metavar="SD",
                        help="every run's identification.xi_guess SD standard deviations of each component off the "
                             "plant file's mean, signs alternating (`wrong_guess`; default 1; 0: none, xi = 0)")
    args = parser.parse_args(argv)
    if args.n < 1 or args.jobs < 1 or (args.paths != "auto" and args.paths < 1):
        parser.error("--n, --jobs and --paths must be positive")
    args.store = (args.store or Path(f"/tmp/random_plants/store-{args.seed}")).resolve()
    out = (args.out or args.store / "random_plants.csv").resolve()

    with tempfile.TemporaryDirectory(prefix="random_plants_") as tmp:
        config_dir = (args.keep_plants or Path(tmp)).resolve()
        start = time.perf_counter()
        plants = draw_plants(args.n, args.seed)
        args.guesses = {p.name: wrong_guess(p, args.seed, args.guess_off) for p in plants} if args.guess_off else {}
        header = f"rdsexp experiments/random_plants.py --seed {args.seed}: plant {{}} of the draw"
        paths = {p.name: write_plant(p, config_dir, header.format(p.index)) for p in plants}
        print_draw(plants, time.perf_counter() - start, config_dir, kept=args.keep_plants is not None)
        if args.only_draw:
            return draw_table(plants)

        args.store.mkdir(parents=True, exist_ok=True)
        log_dir = out.parent / f"{out.stem}_logs"
        log_dir.mkdir(parents=True, exist_ok=True)
        print(f"\nrunning {len(plants)} plants, {args.jobs} at a time, store {args.store}, logs {log_dir}",
              flush=True)
        outcomes: dict[str, Outcome] = {}
        with concurrent.futures.ThreadPoolExecutor(max_workers=args.jobs) as pool:
            futures = {pool.submit(run_plant, args, config_dir, p.name, log_dir): p.name for p in plants}
            for done in concurrent.futures.as_completed(futures):
                o = done.result()
                outcomes[o.plant] = o
                print(f"  {o.plant}: exit {o.returncode}, {o.seconds:.1f} s{', ' + o.note if o.note else ''}",
                      file=sys.stderr, flush=True)
        table = results_table(plants, outcomes)
        for r in table.itertuples():                            # keep the plant of a run that went wrong
            if not _clean(r):
                (log_dir / "plant").mkdir(exist_ok=True)
                shutil.copy(paths[r.plant], log_dir / "plant" / f"{r.plant}.yaml")
        print()
        print_results(table)
        out.parent.mkdir(parents=True, exist_ok=True)
        table.to_csv(out, index=False)
        print(f"table: {out}")
        if not all(_clean(r) for r in table.itertuples()):
            print(f"the plants above that did not end stable: {log_dir / 'plant'} (rerun one with "
                  f"`python -m rdsexp --config-dir {log_dir} plant=NAME`)")
        return table


if __name__ == "__main__":
    main()
