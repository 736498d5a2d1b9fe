"""Report logic of the design studies on hand-made tables: robust_width's per-width summary and the
reproduction rows for Sec. V-B's sentences on other poles and on robust control."""
import sys

import numpy as np
import pandas as pd
from conftest import REPO

sys.path.insert(0, str(REPO / "experiments"))
import reproduction_table  # noqa: E402
import robust_width  # noqa: E402


def frame(narrow_rate=0.99, narrow_loop=0.97):
    """Per-run rows as robust_width.per_run gives them: widths 0.5, 1 (feasible) and 3 (infeasible), 2 seeds."""
    rows = []
    for width, status in ((0.5, "box_optimal"), (1.0, "box_optimal"), (3.0, "infeasible")):
        for seed in (0, 1):
            ok = status != "infeasible"
            rows.append({"width": width, "seed": seed, "status": status, "certified": ok, "lam_box": 0.9 if ok else np.nan,
                         "rate_model": narrow_rate if ok else np.nan, "rate_plant": narrow_rate if ok else np.nan,
                         "lq_cost_plant": 10.0 if ok else np.nan, "h2_plant": 1.0 if ok else np.nan,
                         "max_width": 1.5 + 0.1 * seed, "min_infeasible_width": 1.6 + 0.1 * seed,
                         "proposed_rate_plant": 0.85, "closed_loop_rate": narrow_loop + 0.01 * seed if ok else np.nan,
                         "diverged_fraction": 0.0 if ok else np.nan, "open_loop_rate": 0.95})
    return pd.DataFrame(rows)


def test_robust_width_table_counts_feasible_seeds_and_averages_them():
    table = robust_width.table(frame()).set_index("width")
    assert list(table["certified_seeds"]) == [2, 2, 0]
    assert table.loc[1.0, "rate_true_plant"] == 0.99 and np.isnan(table.loc[3.0, "rate_true_plant"])
    assert table.loc[0.5, "enkf_low"] < table.loc[0.5, "enkf_rate"] == 0.975 < table.loc[0.5, "enkf_high"]
    np.testing.assert_allclose(robust_width.boundary(frame()), (1.5, 1.6, 1.6, 1.7), rtol=1e-12)


def test_robust_control_rows_follow_the_measurements(monkeypatch):
    def rows(f):
        monkeypatch.setattr(robust_width, "per_run", lambda runs: f)
        return {r["number"]: r for r in reproduction_table.design_rows(["run"], None)}
    slow = rows(frame(narrow_loop=0.97))                        # every feasible loop slower than the open loop
    assert slow["robust_control.full_range"]["verdict"] == "reproduced"
    assert slow["robust_control.narrowed"]["verdict"] == "reproduced"
    fast = rows(frame(narrow_rate=0.9, narrow_loop=0.9))        # feasible loops faster than the open loop
    assert fast["robust_control.narrowed"]["verdict"] == "differs"
    assert "4 of 4 runs" in fast["robust_control.narrowed"]["reason"]
    wide_ok = frame()
    wide_ok.loc[wide_ok["width"] == 3.0, ["status", "certified"]] = ["box_optimal", True]
    assert rows(wide_ok)["robust_control.full_range"]["verdict"] == "differs"


def test_other_poles_row_is_reproduced_only_when_no_pole_set_stabilizes():
    def row(stable):
        table = pd.DataFrame([{"plant": "paper", "basis": "reported", "sets": 200, "ms_stabilizing": stable,
                               "ms_stabilizing_fraction": stable / 200, "fraction_low": 0.0, "fraction_high": 0.02,
                               "best_rate_plant": 0.9, "proposed_rate_plant": 0.84}])
        return reproduction_table.design_rows([], table)[0]
    assert row(0)["verdict"] == "reproduced"
    assert row(3)["verdict"] == "differs" and "3/200" in row(3)["rdsexp"]
