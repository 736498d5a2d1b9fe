"""rdsexp.report.sweep_plot on synthetic runs tables (no simulation): the aggregated points against an
independent numpy/scipy computation, failed fractions and runs without a value, heatmap cells, the
files written and their lineage, identical bytes on a second drawing, and one-line errors."""
import hashlib
import json
import warnings

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
import pytest
from scipy import stats

from rdsexp.errors import DamagedRecord, LineageError, RecordWarning
from rdsexp.report import sweep_plot

SIZES, SCALES, SEEDS = (40, 10, 20), (0.5, 2.0), range(5)        # sizes out of order on purpose


def make_table(root, rows):
    """A runs table as `search()` gives it, one run directory with a minimal run.json per row."""
    out = []
    for i, row in enumerate(rows):
        run_dir = root / f"job{i:03d}"
        run_dir.mkdir(parents=True)
        status = row.get("status", "complete")
        info = {"id": f"sweep/{i}", "status": status, "code": {"version": "v1"}}
        if status == "complete":
            info["tables"] = {"metrics": {"file": "metrics.parquet", "sha256": hashlib.sha256(b"%d" % i).hexdigest()}}
        (run_dir / "run.json").write_text(json.dumps(info))
        out.append({"id": info["id"], "sweep": row.get("sweep", "ensemble_size"), "sweep_id": "2025-01-01_abc",
                    "job": i, "status": status, "plant": "paper", "model": "identified", "method": "proposed",
                    "overrides": "", "reused_from": None, "created": f"2025-01-01T00:00:{i:02d}", "code": "v1",
                    "config_hash": f"h{i}", "dir": str(run_dir),
                    **{k: v for k, v in row.items() if k not in ("status", "sweep")}})
    return pd.DataFrame(out)


@pytest.fixture
def sweep(tmp_path):
    """3 ensemble sizes x 2 q scales x 5 seeds; at (10, 2.0) one failed run and one complete run with
    a NaN rate; at (20, 0.5) one run with an infinite rate; failed path fractions vary."""
    rng = np.random.default_rng(7)
    rows = []
    for m in SIZES:
        for q in SCALES:
            for seed in SEEDS:
                rows.append({"metrics.closed_loop_rate": 0.9 + 0.01 * q - 0.001 * m + rng.normal(0, 0.01),
                             "metrics.closed_loop_failed_fraction": float(rng.choice([0.0, 0.25, 0.5])),
                             "params.enkf.ensemble_size": m, "params.enkf.q_scale": q, "params.seed": seed})
                if (m, q, seed) == (10, 2.0, 0):
                    rows[-1].update(status="failed", **{"metrics.closed_loop_rate": np.nan,
                                                        "metrics.closed_loop_failed_fraction": np.nan})
                if (m, q, seed) == (10, 2.0, 1):
                    rows[-1]["metrics.closed_loop_rate"] = np.nan
                if (m, q, seed) == (20, 0.5, 3):
                    rows[-1]["metrics.closed_loop_rate"] = np.inf
    return make_table(tmp_path / "runs", rows)


def expected(values):
    """Mean and 95% t-interval over the finite values, computed here (not with report.seed_interval)."""
    v = np.asarray(values, dtype=float)
    n = v.size
    mean = np.mean(v)
    if n < 2:
        return mean if n else np.nan, np.nan, np.nan, n
    half = stats.t.ppf(0.975, n - 1) * np.std(v, ddof=1) / np.sqrt(n)
    return mean, mean - half, mean + half, n


def test_aggregate_equals_an_independent_computation(sweep):
    points = sweep_plot.aggregate(sweep, "ensemble_size", "closed_loop_rate", hue="q_scale")
    assert list(points.columns) == ["enkf.ensemble_size", "enkf.q_scale", *sweep_plot.POINT_COLUMNS]
    # hue value by hue value, x sorted numerically (the table has 40 first)
    assert list(zip(points["enkf.q_scale"], points["enkf.ensemble_size"])) == [(q, m) for q in SCALES
                                                                               for m in sorted(SIZES)]
    for _, p in points.iterrows():
        at = sweep[(sweep["params.enkf.ensemble_size"] == p["enkf.ensemble_size"])
                   & (sweep["params.enkf.q_scale"] == p["enkf.q_scale"])]
        y = at["metrics.closed_loop_rate"].to_numpy()
        ok = (at["status"] == "complete").to_numpy() & np.isfinite(y)
        mean, low, high, n = expected(y[ok])
        assert (p["mean"], p["low"], p["high"], p["n"]) == (mean, low, high, n)          # exactly
        assert np.allclose([p["low"], p["high"]], stats.t.interval(0.95, n - 1, loc=np.mean(y[ok]),
                                                                    scale=stats.sem(y[ok])), rtol=1e-13, atol=0)
        assert p["runs"] == len(at) == 5
        assert p["failed_runs"] == (~ok).sum() / len(at)
        paths = at["metrics.closed_loop_failed_fraction"].to_numpy()
        assert p["failed_paths"] == np.mean(paths[np.isfinite(paths)])


def test_failed_and_nan_runs_are_left_out_of_the_mean_and_counted(sweep):
    points = sweep_plot.aggregate(sweep, "ensemble_size", "closed_loop_rate", hue="q_scale").set_index(
        ["enkf.ensemble_size", "enkf.q_scale"])
    assert points.loc[(10, 2.0), "n"] == 3 and points.loc[(10, 2.0), "failed_runs"] == 2 / 5    # failed + NaN
    assert points.loc[(20, 0.5), "n"] == 4 and points.loc[(20, 0.5), "failed_runs"] == 1 / 5    # inf
    assert (points.drop([(10, 2.0), (20, 0.5)])["failed_runs"] == 0).all()
    assert np.isfinite(points[["mean", "low", "high"]].to_numpy()).all()
    # the failed run has no failed-path fraction: the mean over the other four
    at = sweep[(sweep["params.enkf.ensemble_size"] == 10) & (sweep["params.enkf.q_scale"] == 2.0)]
    assert points.loc[(10, 2.0), "failed_paths"] == np.mean(at["metrics.closed_loop_failed_fraction"].iloc[1:])


def test_points_without_values_one_value_and_no_failed_path_column(tmp_path):
    rows = [{"metrics.lam": v, "params.enkf.ensemble_size": m, "params.seed": s}
            for m, values in ((10, [np.nan, np.nan]), (20, [0.5, np.nan]), (40, [0.25, 0.75])) for s, v in enumerate(values)]
    table = make_table(tmp_path, rows)
    points = sweep_plot.aggregate(table, "enkf.ensemble_size", "lam")
    assert points["n"].tolist() == [0, 1, 2] and points["failed_runs"].tolist() == [1.0, 0.5, 0.0]
    assert np.isnan(points.loc[0, ["mean", "low", "high"]].astype(float)).all()
    assert points.loc[1, "mean"] == 0.5 and np.isnan(points.loc[1, ["low", "high"]].astype(float)).all()
    assert points["failed_paths"].isna().all()              # the table has no closed_loop_failed_fraction
    spec = sweep_plot._spec(table, "enkf.ensemble_size", "lam", None)
    fig = sweep_plot._lines(spec, points, logx=True, logy=False)
    ax, ax_fail = fig.axes
    assert [t.get_text() for t in ax.texts] == ["n=0 of 2", "n=1 of 2", "n=2"]
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["runs without a value"]
    plt.close(fig)


def test_keys_resolve_like_search_and_categories_keep_their_order(sweep):
    a = sweep_plot.aggregate(sweep, "ensemble_size", "closed_loop_rate", hue="q_scale")
    b = sweep_plot.aggregate(sweep, "params.enkf.ensemble_size", "metrics.closed_loop_rate", hue="params.enkf.q_scale")
    pd.testing.assert_frame_equal(a, b)
    assert a["enkf.ensemble_size"].tolist()[:3] == [10, 20, 40]
    sweep["params.gain.source"] = np.where(sweep["params.enkf.ensemble_size"] == 40, "reported", "identified")
    one = sweep[sweep["params.enkf.q_scale"] == sweep["params.enkf.q_scale"].iloc[0]].drop(columns="params.enkf.q_scale")
    assert sweep_plot.aggregate(one, ["gain.source", "ensemble_size"], "closed_loop_rate")[
        "gain.source"].unique().tolist() == ["reported", "identified"]    # order of appearance, not sorted


def test_heatmap_cells(sweep):
    points = sweep_plot.aggregate(sweep, ["ensemble_size", "q_scale"], "closed_loop_rate")
    assert list(points.columns[:2]) == ["enkf.ensemble_size", "enkf.q_scale"] and len(points) == 6
    spec = sweep_plot._spec(sweep, ["ensemble_size", "q_scale"], "closed_loop_rate", None)
    fig = sweep_plot._heatmap(spec, points, logy=False)
    ax = fig.axes[0]
    grid = ax.images[0].get_array()
    texts = {(t.get_position()): t.get_text() for t in ax.texts}
    for i, q in enumerate(SCALES):
        for j, m in enumerate(sorted(SIZES)):
            at = sweep[(sweep["params.enkf.ensemble_size"] == m) & (sweep["params.enkf.q_scale"] == q)]
            y = at["metrics.closed_loop_rate"].to_numpy()
            ok = (at["status"] == "complete").to_numpy() & np.isfinite(y)
            assert grid[i, j] == expected(y[ok])[0]
            count = f"n={ok.sum()}" if ok.all() else f"n={ok.sum()} of {len(at)}"
            assert texts[(j, i)].split("\n")[:2] == [f"{np.mean(y[ok]):.4g}", count]
    assert [t.get_text() for t in ax.get_xticklabels()] == ["10", "20", "40"]
    assert [t.get_text() for t in ax.get_yticklabels()] == ["0.5", "2"]
    plt.close(fig)


def test_files_and_lineage_name_exactly_the_runs_drawn(sweep, tmp_path):
    sweep.loc[0, "params.enkf.q_scale"] = np.nan                   # cannot be placed: left out, named
    with pytest.warns(RecordWarning, match=r"1 run\(s\) without a value of params.enkf.q_scale left out"):
        paths = sweep_plot.plot(sweep, "ensemble_size", "closed_loop_rate", hue="q_scale", logx=True,
                                out=tmp_path / "fig")
    names = [p.name for p in paths]
    assert names == [f"closed_loop_rate_vs_ensemble_size.{ext}" for ext in ("png", "pdf", "caption.md", "csv", "json")]
    assert all(p.stat().st_size > 0 for p in paths)
    lineage = json.loads(paths[-1].read_text())
    drawn = sweep.iloc[1:]
    assert [(r["id"], r["dir"]) for r in lineage["runs"]] == list(zip(drawn["id"], drawn["dir"]))
    for entry in lineage["runs"]:
        run_json = (tmp_path / entry["dir"] / "run.json").read_bytes()
        assert entry["run_json_sha256"] == hashlib.sha256(run_json).hexdigest()
        recorded = (json.loads(run_json).get("tables") or {}).get("metrics")
        assert entry["tables"] == ({"metrics": recorded["sha256"]} if recorded else {})
    assert any(entry["tables"] == {} for entry in lineage["runs"])          # the failed run is drawn too
    assert lineage["left_out"] == [{"id": sweep.loc[0, "id"], "dir": sweep.loc[0, "dir"]}]
    assert lineage["code_version"] == "v1" and lineage["outputs"] == names[:-1]
    assert lineage["columns"] == {"x": ["params.enkf.ensemble_size"], "y": "metrics.closed_loop_rate",
                                  "hue": "params.enkf.q_scale"}
    csv = pd.read_csv(paths[3])
    assert csv["n"].sum() == (drawn["status"].eq("complete") & np.isfinite(drawn["metrics.closed_loop_rate"])).sum()
    assert "| enkf.ensemble_size | enkf.q_scale | mean |" in paths[2].read_text()


@pytest.mark.slow
def test_drawing_twice_gives_identical_bytes(sweep, tmp_path):
    first = sweep_plot.plot(sweep, ["ensemble_size", "q_scale"], "closed_loop_rate", out=tmp_path / "a", name="grid")
    second = sweep_plot.plot(sweep, ["ensemble_size", "q_scale"], "closed_loop_rate", out=tmp_path / "b", name="grid")
    for a, b in zip(first, second):
        assert a.read_bytes() == b.read_bytes(), a.name    # PNG, PDF, caption, points and lineage
    again = sweep_plot.plot(sweep, "ensemble_size", "closed_loop_rate", hue="q_scale", out=tmp_path / "c")
    assert again[0].read_bytes() == sweep_plot.plot(sweep, "ensemble_size", "closed_loop_rate", hue="q_scale",
                                                    out=tmp_path / "d")[0].read_bytes()


@pytest.mark.parametrize("call, message", [
    (dict(x="nope", y="closed_loop_rate"), "x: 'nope' names no column of the runs table"),
    (dict(x="ensemble_size", y="nope"), "y: 'nope' names no column of the runs table"),
    (dict(x="ensemble_size", y="closed_loop_rate", hue="nope"), "hue: 'nope' names no column of the runs table"),
    (dict(x=["ensemble_size", "nope"], y="closed_loop_rate"), "x: 'nope' names no column of the runs table"),
    (dict(x=["ensemble_size", "q_scale", "seed"], y="closed_loop_rate"), "x must be a key or a list of two keys"),
    (dict(x=["ensemble_size", "params.enkf.ensemble_size"], y="closed_loop_rate"), "x names the same column twice"),
    (dict(x="ensemble_size", y="closed_loop_verdict"), "y 'closed_loop_verdict' (metrics.closed_loop_verdict) is not a number"),
    (dict(x=["ensemble_size", "q_scale"], y="closed_loop_rate", hue="seed"), "hue does not apply to a heatmap"),
    (dict(x="plant", y="closed_loop_rate", logx=True, one=True), "logx: plant has values that are not positive numbers"),
    (dict(x=["ensemble_size", "q_scale"], y="closed_loop_rate", logx=True), "logx does not apply to a heatmap"),
    (dict(x="ensemble_size", y="closed_loop_rate", logy=True, negative=True, one=True), "logy: the mean of closed_loop_rate is not positive"),
])
def test_bad_requests_fail_with_one_line_before_drawing(sweep, tmp_path, call, message):
    sweep["metrics.closed_loop_verdict"] = "stable"
    if call.pop("negative", False):
        sweep["metrics.closed_loop_rate"] -= 1
    if call.pop("one", False):          # one setting but the key drawn (a point pools seeds only)
        sweep = sweep[(sweep["params.enkf.q_scale"] == sweep["params.enkf.q_scale"].iloc[0])
                      & ((call["x"] != "plant") | (sweep["params.enkf.ensemble_size"] == 10))]
    with pytest.raises(ValueError, match="^" + message.replace("(", r"\(").replace(")", r"\)")) as err:
        sweep_plot.plot(sweep, out=tmp_path / "fig", **call)
    assert "\n" not in str(err.value)
    assert not (tmp_path / "fig").exists()


def test_empty_table_and_missing_identity_columns(sweep, tmp_path):
    with pytest.raises(ValueError, match="^the runs table is empty: nothing to plot$"):
        sweep_plot.plot(sweep.iloc[:0], "ensemble_size", "closed_loop_rate", out=tmp_path)
    with pytest.raises(ValueError, match="^the runs table is empty"):
        sweep_plot.aggregate(sweep.iloc[:0], "ensemble_size", "closed_loop_rate")
    with pytest.raises(ValueError, match=r"^the runs table has no dir column \(pass rdsexp.runs.search\(\) output\)$"):
        sweep_plot.aggregate(sweep.drop(columns="dir"), "ensemble_size", "closed_loop_rate")
    sweep["params.enkf.ensemble_size"] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RecordWarning)
        with pytest.raises(ValueError, match="^no run has a value of params.enkf.ensemble_size$"):
            sweep_plot.aggregate(sweep, "ensemble_size", "closed_loop_rate")


def test_a_run_json_that_is_missing_or_names_another_run_stops_the_figure(sweep, tmp_path):
    other = sweep.copy()
    other.loc[3, "id"] = "someone/else"
    with pytest.raises(LineageError, match="names run 'sweep/3', the runs table 'someone/else'"):
        sweep_plot.plot(other, "ensemble_size", "closed_loop_rate", hue="q_scale", out=tmp_path / "fig")
    (tmp_path / sweep.loc[5, "dir"] / "run.json").unlink()
    with pytest.raises(DamagedRecord, match="run.json: missing"):
        sweep_plot.plot(sweep, "ensemble_size", "closed_loop_rate", hue="q_scale", out=tmp_path / "fig")
    assert not (tmp_path / "fig").exists()


@pytest.mark.parametrize("column, value, what", [("plant_hash", "66772176229f", "plants"),
                                                 ("params.closed_loop.paths", 50, "settings"),
                                                 ("params.identification.passes", 10, "settings")])
def test_a_point_that_would_pool_other_plants_or_path_counts_is_refused(sweep, tmp_path, column, value, what):
    """Two plant files of one name that differ, a 50-path run among 30-path ones, or any other setting that differs
    under one point or cell (not the seed, not the key drawn): one line naming the point, the key and its values,
    nothing drawn; split by hue (lines) or selected, it draws."""
    sweep = sweep[sweep["params.enkf.q_scale"] == sweep["params.enkf.q_scale"].iloc[0]].copy()   # one setting
    sweep[column] = sweep.get(column, pd.Series(["d238f1965554" if column == "plant_hash" else 30] * len(sweep),
                                                index=sweep.index))
    sweep.loc[sweep["params.enkf.ensemble_size"] == 40, column] = \
        np.where(sweep.loc[sweep["params.enkf.ensemble_size"] == 40, "params.seed"] == 2, value, sweep[column].iloc[0])
    for x in ("ensemble_size", ["ensemble_size", "q_scale"]):
        with pytest.raises(ValueError, match=f"^{what} differ within the point params.enkf.ensemble_size=40") as err:
            sweep_plot.plot(sweep, x=x, y="closed_loop_rate", out=tmp_path / "fig")
        assert "\n" not in str(err.value) and "hue=" in str(err.value)
    assert not (tmp_path / "fig").exists()
    sweep_plot.plot(sweep, x="ensemble_size", y="closed_loop_rate", hue=column, out=tmp_path / "split")
    sweep_plot.plot(sweep[sweep[column] != value], x="ensemble_size", y="closed_loop_rate", out=tmp_path / "one")
