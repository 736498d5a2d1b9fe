"""Data runs: recorded (u, y) in place of the plant (`rdsexp data=FILE model=NAME`), the export of a run's
identification in the data format, the round trip between them, provenance and the bad-data errors."""
import json
import re

import numpy as np
import pandas as pd
import pytest

from rdsexp.errors import ConfigError
from rdsexp.experiment import data as datafile
from rdsexp.runs import main as runs_main
from tests.conftest import SMALL, rdsexp


def runs_of(cwd):
    return sorted((cwd / "outputs" / "runs").iterdir())


def info_of(run_dir):
    return json.loads((run_dir / "run.json").read_text())


def model_values(run_dir):
    return pd.read_parquet(run_dir / "model.parquet")["value"].to_numpy()


@pytest.fixture(scope="module")
def round_trip(tmp_path_factory):
    """The paper's experiment (small), its identification exported, and the data run on the file."""
    cwd = tmp_path_factory.mktemp("roundtrip")
    rdsexp(*SMALL, cwd=cwd)
    (original,) = runs_of(cwd)
    assert runs_main(["export", "--data", str(original), "--out", str(cwd / "d.csv")]) == 0
    proc = rdsexp("data=d.csv", "model=paper", "plant=paper", *SMALL, cwd=cwd)     # the paper's method lines
    (data_run,) = [r for r in runs_of(cwd) if r != original]
    return cwd, original, data_run, proc


def test_round_trip_gives_the_runs_moments(round_trip):
    """Paper's plant, open-loop identification: identifying from the exported file gives the run's moments to
    1e-12 (the same EnKF streams and initial ensemble; here bit for bit) and the same proposed gain."""
    cwd, original, data_run, _ = round_trip
    a, b = model_values(original), model_values(data_run)
    assert a.shape == b.shape and np.max(np.abs(a - b)) <= 1e-12
    ga = pd.read_parquet(original / "gains.parquet").set_index(["distribution", "method"])
    gb = pd.read_parquet(data_run / "gains.parquet").set_index(["distribution", "method"])
    np.testing.assert_allclose(gb.loc[("identified", "proposed"), "lam"], ga.loc[("identified", "proposed"), "lam"],
                               rtol=1e-9)
    table = pd.read_csv(cwd / "d.csv")
    assert list(table.columns) == ["path", "k", "u[0]", "y[0]", "y[1]", "y[2]"] and len(table) == 31


def test_data_run_claims_no_true_plant(round_trip):
    """No plant anywhere: no true-plant number in run.json, no loop, the summary says every rate is on the
    identified model, each design with its spread over the moments' draws."""
    _, _, data_run, proc = round_trip
    info = info_of(data_run)
    s = info["summary"]
    assert s["plant"] is None and "rate_plant" not in s and "plant_xi_mean" not in s and "xi_crps" not in s
    assert not any(k.startswith(("closed_loop", "open_loop")) for k in s)
    rates = s["design_rates"]["proposed"]
    assert rates["rate_model_q05"] <= rates["rate_model_median"] <= rates["rate_model_q95"] <= rates["rate_model_worst"]
    assert s["modeling_uncertainty"]["over"] == "window blocks"       # one recorded path
    gains = pd.read_parquet(data_run / "gains.parquet")
    assert gains[["rate_plant", "lq_cost_plant", "h2_plant"]].isna().all().all()
    assert "no plant: every rate below is exact on the identified model" in proc.stdout
    assert "true plant" not in proc.stdout


@pytest.mark.slow
def test_data_run_provenance_reuse_and_verify(round_trip):
    """run.json records the file's sha256, rows and column map; the catalog shows the file as the identity;
    verify re-runs from the file; a changed file is another config (never reused) and fails verify."""
    cwd, original, data_run, _ = round_trip
    info = info_of(data_run)
    assert info["data"]["sha256"] == datafile.file_sha256(cwd / "d.csv") and info["data"]["rows"] == 31
    assert info["data"]["columns"] == {"path": "path", "k": "k", "u": ["u[0]"], "y": ["y[0]", "y[1]", "y[2]"],
                                       "d": []}
    assert info["plant_hash"] is None
    listed = rdsexp("list", "--csv", module="rdsexp.runs", cwd=cwd).stdout
    assert f"data:d.csv,{info['data']['sha256'][:12]}" in listed
    ok = rdsexp("verify", str(data_run), module="rdsexp.runs", cwd=cwd, check=False)
    assert ok.returncode == 0 and "verify: identical" in ok.stdout
    table = pd.read_csv(cwd / "d.csv")
    table.loc[3, "y[0]"] += 1e-9
    table.to_csv(cwd / "d.csv", index=False, float_format="%.17g")
    changed = rdsexp("verify", str(data_run), module="rdsexp.runs", cwd=cwd, check=False)
    assert changed.returncode != 0 and "has changed since the run" in changed.stdout
    rdsexp("data=d.csv", "model=paper", "plant=paper", *SMALL, cwd=cwd)
    newest = info_of(runs_of(cwd)[-1])
    assert newest["config_hash"] != info["config_hash"] and not newest.get("reused_from")


def write(path, rows: dict):
    pd.DataFrame(rows).to_csv(path, index=False)


def good(paths=2, steps=6):
    k = np.tile(np.arange(steps), paths)
    return {"path": np.repeat(np.arange(paths), steps), "k": k, "u[0]": np.ones(paths * steps),
            "y[0]": np.linspace(0, 1, paths * steps), "y[1]": np.zeros(paths * steps)}


def defect(change):
    rows = {k: np.array(v, dtype=float if k not in ("path", "k") else None) for k, v in good().items()}
    change(rows)
    return rows


BAD = {
    "missing column": (lambda r: r.pop("y[1]"), r"column y\[1\]: missing \(the model has outputs ny = 2\)"),
    "missing k": (lambda r: r.pop("k"), r"column k: missing"),
    "nan": (lambda r: r["y[0]"].__setitem__(4, np.nan), r"row 6, column y\[0\]: nan is not a finite number"),
    "inf": (lambda r: r["u[0]"].__setitem__(7, np.inf), r"row 9, column u\[0\]: inf is not a finite number"),
    "k not increasing": (lambda r: r["k"].__setitem__(3, 1), r"row 5, column k: k = 1 in path 0, expected 3"),
    "row written twice": (lambda r: [r.__setitem__(c, np.insert(v, 4, v[3])) for c, v in list(r.items())],
                          r"row 6, column k: path 0, k = 3 repeats row 5"),
    "too wide": (lambda r: r.__setitem__("u[1]", np.ones(12)), r"column u\[1\]: the model has inputs m = 1"),
    "too short": (lambda r: None, r"path 0 has 6 recorded steps, fewer than the window needs \(K0 \+ K1 \+ 1 = 8\)"),
}


@pytest.mark.parametrize("case", BAD, ids=BAD)
def test_bad_data_is_one_line_naming_file_row_column(tmp_path, case):
    """One DataError line with the file, the row as a spreadsheet numbers it (the header is row 1) and the column."""
    change, message = BAD[case]
    path = tmp_path / "bad.csv"
    write(path, defect(change))
    need = 8 if case == "too short" else 6
    with pytest.raises(ConfigError, match=message) as err:
        datafile.load(path, m=1, ny=2, min_steps=need)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_ragged_paths_are_cut_to_the_shortest_and_unreadable_files_fail(tmp_path):
    rows = pd.DataFrame(good(paths=2, steps=8))
    rows = rows[~((rows["path"] == 1) & (rows["k"] >= 6))]
    rows.to_csv(tmp_path / "ragged.csv", index=False)
    loaded = datafile.load(tmp_path / "ragged.csv", m=1, ny=2, min_steps=6)
    assert loaded.recorded.steps == 6 and loaded.recorded.paths == 2 and loaded.rows == 14
    (tmp_path / "broken.parquet").write_bytes(b"not parquet")
    with pytest.raises(ConfigError, match=r"broken.parquet: unreadable"):
        datafile.load(tmp_path / "broken.parquet", m=1, ny=2, min_steps=6)
    with pytest.raises(ConfigError, match=r"nothing.csv: unreadable \(no such file\)"):
        datafile.load(tmp_path / "nothing.csv", m=1, ny=2, min_steps=6)


def test_bad_data_on_the_command_line_exits_2_and_records_nothing(tmp_path):
    rows = pd.DataFrame(good(paths=1, steps=31)).assign(**{"y[2]": 0.0})
    rows.loc[2, "y[0]"] = np.nan
    rows.to_csv(tmp_path / "bad.csv", index=False)
    proc = rdsexp("data=bad.csv", "model=paper", *SMALL, cwd=tmp_path, check=False)
    assert proc.returncode == 2
    assert re.match(r"rdsexp: data error: data.file: \S*bad.csv, row 4, column y\[0\]", proc.stderr)   # header: 1
    assert not (tmp_path / "outputs" / "runs").exists() or not any((tmp_path / "outputs" / "runs").iterdir())


def test_dropout_example_with_holdout_validation(tmp_path):
    """The shipped example: recorded dropout loops (30 paths), 20% held out; the identification batches the other
    24, the moments' spread is a bootstrap over them, and the validation table scores the one-step-ahead
    predictive ensembles of y on the 6 held-out paths under the modeled law and the nominal model."""
    from tests.conftest import REPO
    example = REPO / "examples" / "dropout"
    proc = rdsexp("--config-dir", str(example), f"data={example / 'dropout.csv'}", "model=dropout",
                  "data.holdout=0.2", "enkf.ensemble_size=20", "identification.passes=1", "data.loops=true",
                  "closed_loop.paths=10", "closed_loop.floor_paths=5", cwd=tmp_path)
    (run_dir,) = runs_of(tmp_path)
    s = info_of(run_dir)["summary"]
    assert s["data"]["identification_paths"] == 24 and s["data"]["holdout_paths"] == 6
    # the simulated estimator's replicates replay the 24 paths' recorded inputs open loop; these were recorded under
    # a stabilizing gain, so no law reproduces their outputs (their energy, their correlation in time): misfit, the
    # window's moments kept, said so
    estimator = s["modeling_estimator"]
    assert s["modeling_status"] == "misfit" and estimator["summary_paths"] == 24 and "noise_sensitivity" not in s
    assert estimator["misfit"]["summary"].endswith("of y[0]") and abs(estimator["misfit"]["z"]) > 4
    assert s["xi_mean"] == estimator["summary_mean"] and s["modeling_uncertainty"]["over"] == "the prior box"
    assert "read on 24 recorded paths" in proc.stdout and "misfit: no law the replicates tried" in proc.stdout
    table = pd.read_parquet(run_dir / "validation.parquet")
    assert set(table["law"]) == {"modeled", "nominal"} and set(table["output"]) == {"0", "all"}
    assert table[["coverage_50", "coverage_90"]].apply(lambda c: c.between(0, 1)).all().all()
    assert (table["crps"] > 0).all() and (table["paths"] == 6).all()
    v = s["validation"]
    assert v["modeled_better"] == (v["modeled"]["crps"] < v["nominal"]["crps"])
    assert "validation on 6 held-out paths" in proc.stdout
    assert "true plant" not in proc.stdout
    # data.loops: the loops simulated on the identified model, named and labelled so in every table and summary
    loops = s["loops_on_model"]
    assert loops["label"] == "simulated on the model, not the plant"
    assert set(loops) >= {"closed_loop_on_model", "open_loop_on_model"}
    assert "rate_plant" not in s and not any(k.startswith(("closed_loop_", "open_loop_")) for k in s)
    metrics = pd.read_parquet(run_dir / "metrics.parquet")
    assert list(metrics["experiment"]) == ["closed_loop_on_model", "open_loop_on_model"]
    assert set(pd.read_parquet(run_dir / "trajectories.parquet")["experiment"]) == set(metrics["experiment"])
    assert "closed loop on model (simulated on the model, not the plant)" in proc.stdout


def test_recorded_paths_whose_estimate_fails_are_left_out(round_trip):
    """Several recorded paths, one of which makes the EnKF's estimate diverge: the moments come from the others,
    and the summary says how many were left out and why."""
    cwd = round_trip[0]
    one = pd.read_csv(cwd / "d.csv")
    wild = one.assign(path=1, **{f"y[{i}]": one[f"y[{i}]"] * 1e9 * (1 + one["k"]) for i in range(3)})
    pd.concat([one, wild, one.assign(path=2)]).to_csv(cwd / "three.csv", index=False, float_format="%.17g")
    rdsexp("data=three.csv", "model=paper", "plant=paper", *SMALL, cwd=cwd)
    s = info_of(max(runs_of(cwd), key=lambda r: r.stat().st_mtime))["summary"]
    assert s["identification_failed_paths"]["count"] == 1 and s["identification_failed_paths"]["of"] == 3
    assert s["modeling_status"] == "ok" and s["modeling_uncertainty"]["over"] == "paths"


def test_a_data_run_bounds_the_effect_of_the_noise_its_enkf_assumes(tmp_path):
    """identification.noise_sensitivity (auto: x0.1 and x10 in a data run with the paper's estimator): the moments modeled again with enkf.Q's
    x block and enkf.R scaled; the x1 row is the run's own moments, and the x10 row is exactly what a data run
    configured with that noise models (same seeds: recomputed here from the config alone)."""
    from tests.conftest import REPO
    example = REPO / "examples" / "dropout"
    common = ["--config-dir", str(example), f"data={example / 'dropout.csv'}", "model=dropout",
              "enkf.ensemble_size=20", "identification.passes=1", "identification.resamples=20",
              "identification.estimator=paper"]         # (the simulated estimator estimates the noise instead)
    for where in ("base", "scaled"):
        (tmp_path / where).mkdir()
    proc = rdsexp(*common, cwd=tmp_path / "base")
    (run_dir,) = runs_of(tmp_path / "base")
    s = info_of(run_dir)["summary"]
    v = s["noise_sensitivity"]
    assert v["scales"] == [0.1, 1.0, 10.0] and v["xi_mean"][1] == s["xi_mean"] and v["xi_std"][1] == s["xi_std"]
    assert v["range_over_sd"] > 0 and "with the EnKF's assumed noise (enkf.Q's x block and R) x0.1 / x1 / x10" \
        in proc.stdout
    rdsexp(*common, "enkf.Q.x=0.1", "enkf.R=0.1", "identification.noise_sensitivity=[]", cwd=tmp_path / "scaled")
    (scaled,) = runs_of(tmp_path / "scaled")
    t = info_of(scaled)["summary"]
    assert "noise_sensitivity" not in t
    assert t["xi_mean"] == v["xi_mean"][2] and t["xi_std"] == v["xi_std"][2]
    with pytest.raises(AssertionError, match="noise_sensitivity"):
        rdsexp(*common, "identification.noise_sensitivity=[0]", cwd=tmp_path)


def test_the_docs_sample_file_is_valid_data_for_the_shipped_model():
    """docs/data/sample.csv, the sample the data page offers: the first 3 paths of the shipped example, read as a
    data run reads it with the example's model (m = 1, ny = 1) and the default window (101 steps)."""
    from tests.conftest import REPO
    sample = datafile.load(REPO / "docs" / "data" / "sample.csv", m=1, ny=1, min_steps=101)
    example = datafile.load(REPO / "examples" / "dropout" / "dropout.csv", m=1, ny=1, min_steps=101)
    assert sample.recorded.paths == 3 and sample.recorded.steps == 101
    np.testing.assert_array_equal(sample.recorded.y, example.recorded.y[:, :3])
    np.testing.assert_array_equal(sample.recorded.u, example.recorded.u[:, :3])


def test_a_data_run_needs_no_plant_wherever_it_is_started(round_trip, tmp_path):
    """`rdsexp data=FILE model=NAME` as the README writes it, from a directory outside the checkout and without a
    plant: the data defaults (plant group `recorded`: no system, rdsexp's defaults for a system of one's own, the
    simulated estimator), recorded in run.json's overrides so that verify re-runs the same."""
    cwd, *_ = round_trip
    proc = rdsexp(f"data={cwd / 'd.csv'}", "model=paper", *SMALL, "identification.replicates=100", cwd=tmp_path)
    (run_dir,) = runs_of(tmp_path)
    info = info_of(run_dir)
    assert info["status"] == "complete" and "plant=recorded" in info["overrides"]
    assert info["summary"]["modeling_estimator"]["name"] == "simulated" and "  data d.csv (sha256" in proc.stdout
