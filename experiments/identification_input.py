"""Which identification input is consistent with all the paper's modeled moments together?

The paper says only "a maximal length sequence" (Sec. V-A). For every identification-input setting
of the latest `identification_input` sweep (levels, amplitude, hold, register, ... : every
identification.input key that varies), over its seeds: the modeled mean and covariance of xi
(eqs. ex-mean, ex-covar), mean with a 95% t-interval over seeds, and the standardised distance of
the paper's single draw from the seeds' distribution, z = (paper - mean) / (sd sqrt(1 + 1/n))
(a prediction interval for one more seed). A setting is consistent when every one of the 9 moments
(3 means, 6 covariance entries) has |z| below the t quantile at the Bonferroni level 0.05 / 9, i.e.
the paper's draw lies in the joint 95% prediction region of one seed.

    python experiments/identification_input.py [--root outputs] [--out outputs/report]
"""
import numpy as np
import pandas as pd
from scipy import stats

from rdsexp import report

NAME = "identification_input"
SWEEP = "identification_input"
LEVEL = 0.95
MOMENTS = [("mean", i, 0) for i in range(3)] + [("cov", i, j) for i in range(3) for j in range(i, 3)]


def setting(run: report.Run) -> str:
    """The run's identification input, e.g. 'unipolar, amplitude 10, hold 1, register 7'."""
    node = run.get("identification.input")
    text = f"{node.get('levels', 'bipolar')}, amplitude {node['amplitude']:g}, hold {node.get('hold', 1)}, " \
           f"register {node['register_length']}"
    extras = [f"{k} {node[k]}" for k in ("taps", "state", "seed") if node.get(k) is not None]
    return ", ".join([text, *extras])


def moments(run: report.Run) -> np.ndarray:
    """The 9 modeled moments of a run (NaN where modeling failed), in the order of MOMENTS."""
    m = run.table("model")
    out = []
    for quantity, i, j in MOMENTS:
        v = m[(m["quantity"] == quantity) & (m["row"] == i) & (m["col"] == j)]["value"]
        out.append(v.iloc[0] if len(v) else np.nan)
    return np.array(out)


def paper_moments() -> np.ndarray:
    ref = report.reference()["modeling"]
    return np.array([ref["xi_mean"][i] if q == "mean" else ref["xi_cov"][i][j] for q, i, j in MOMENTS])


def name(quantity: str, i: int, j: int) -> str:
    return f"mean xi{i + 1}" if quantity == "mean" else (f"var xi{i + 1}" if i == j else f"cov xi{i + 1},xi{j + 1}")


def build(runs: list[report.Run]) -> pd.DataFrame:
    """One row per setting: per moment 'mean [low, high]' over seeds and z; max |z|; consistent."""
    paper = paper_moments()
    groups: dict[str, list] = {}
    for r in sorted(runs, key=lambda r: (setting(r), r.get("seed"))):
        groups.setdefault(setting(r), []).append(moments(r))
    rows = []
    for text, values in groups.items():
        v = np.array(values)
        v = v[np.all(np.isfinite(v), axis=1)]
        n = len(v)
        row = {"setting": text, "seeds": len(values), "modeled_seeds": n}
        if n >= 2:
            mean, sd = v.mean(axis=0), v.std(axis=0, ddof=1)
            half = stats.t.ppf(0.5 + LEVEL / 2, n - 1) * sd / np.sqrt(n)
            z = (paper - mean) / (sd * np.sqrt(1 + 1 / n))
            bound = stats.t.ppf(1 - (1 - LEVEL) / (2 * len(MOMENTS)), n - 1)
            for (q, i, j), m_, h_, z_ in zip(MOMENTS, mean, half, z):
                row[name(q, i, j)] = f"{m_:.4f} [{m_ - h_:.4f}, {m_ + h_:.4f}]"
                row[f"z {name(q, i, j)}"] = round(float(z_), 2)
            row["max_abs_z"] = float(np.max(np.abs(z)))
            row["z_bound"] = float(bound)
            row["consistent"] = bool(np.max(np.abs(z)) <= bound)
        else:
            row["consistent"] = False
        rows.append(row)
    return pd.DataFrame(rows)


def consistent_settings(table: pd.DataFrame) -> list[str]:
    return list(table[table["consistent"]]["setting"])


def verdict(table: pd.DataFrame, configured: str | None = None) -> str:
    """One paragraph for the report: which settings are consistent, the closest one otherwise."""
    ok = consistent_settings(table)
    seeds = int(table["seeds"].max()) if len(table) else 0
    text = (f"Each row: one identification input, over its seeds (up to {seeds}); per moment the mean over seeds "
            "with its 95% t-interval and z = (paper - mean) / (sd sqrt(1 + 1/n)), the paper's single draw "
            "against one more seed. Consistent: all 9 |z| below the Bonferroni bound (joint 95% prediction "
            "region). ")
    if ok:
        best = table[table["consistent"]].sort_values("max_abs_z").iloc[0]
        text += ("Consistent with all the paper's modeled moments together: "
                 + "; ".join(f"{s} (max |z| {z:.2f})" for s, z in table[table["consistent"]][["setting", "max_abs_z"]]
                             .itertuples(index=False))
                 + f" (bound {best['z_bound']:.2f}). The closest: {best['setting']}.")
    elif "max_abs_z" in table and table["max_abs_z"].notna().any():
        best = table.loc[table["max_abs_z"].idxmin()]
        text += (f"No swept setting is consistent with all the paper's modeled moments together; the closest is "
                 f"{best['setting']} (max |z| {best['max_abs_z']:.2f} > {best['z_bound']:.2f}).")
    else:
        text += "No setting has two modeled seeds."
    if configured is not None:
        text += f" The paper config uses: {configured}."
    return text


def main(argv=None):
    args = report.arguments(__doc__.splitlines()[0], argv)
    runs = report.sweep_runs(args.root, SWEEP, args.allow_mixed)
    table = build(runs)
    report.write_table(table, args.out, NAME, runs, __file__)
    paper = report.load_runs(args.root, report.PAPER_SWEEP)
    configured = setting(report.first_seed(paper)) if report.select(paper, gain__method="proposed") else None
    report.write_caption(args.out, NAME, verdict(table, configured))
    return table


if __name__ == "__main__":
    report.script(main)
