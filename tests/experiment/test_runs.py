"""rdsexp.runs: search, list, diff, show and load over stored run directories."""
import io
import json
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from conftest import rdsexp
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from rdsexp import runs


def fake_run(root, sweep, job, overrides, summary, tables=None):
    """A run directory as the runner writes it: .hydra/config.yaml (the composed config) and run.json."""
    run_dir = root / sweep / str(job)
    (run_dir / ".hydra").mkdir(parents=True)
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        OmegaConf.save(compose("config", overrides=overrides), run_dir / ".hydra" / "config.yaml")
    info = {"id": f"{sweep}/{job}", "status": "complete", "created": f"2026-01-01T00:{sweep}:{job:02d}",
            "sweep": {"dir": str(root / sweep), "job": job, "name": "noise"}, "config_hash": f"h{sweep}{job}",
            "code": {"version": "abc"}, "summary": summary, "tables": tables or {}, "seconds": 1.0 + job}
    (run_dir / "run.json").write_text(json.dumps(info))
    return run_dir


def summary(lam, rate, status="ok"):
    return {"plant": "paper", "gain_method": "proposed", "lam": lam, "xi_mean": [0.4, 0.2],
            "closed_loop_status": status, "closed_loop_rate": [rate, rate - 0.01, rate + 0.01], "designs": {}}


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    root = tmp_path_factory.mktemp("outputs")
    for sweep, seed in (("A", 0), ("B", 1)):
        for job, q in enumerate((0.25, 1.0, 4.0)):
            fake_run(root, sweep, job, [f"enkf.q_scale={q}", f"seed={seed}"],
                     summary(0.8 + 0.01 * job + 0.001 * seed, 0.9 + 0.02 * job, "ok" if q < 4 else "failed"))
    return root


def test_search_has_params_and_metrics_per_run(root):
    table = runs.search(root)
    assert list(table["id"]) == [f"{s}/{j}" for s in "AB" for j in range(3)]
    assert list(table["params.enkf.q_scale"]) == [0.25, 1.0, 4.0] * 2
    assert list(table["params.seed"]) == [0, 0, 0, 1, 1, 1]
    assert table["params.enkf.ensemble_size"].eq(300).all() and table["params.gain.method"].eq("proposed").all()
    assert table["params.closed_loop.rate_window"].eq("[0.6, 0.8]").all()      # short lists as text
    np.testing.assert_allclose(table["metrics.closed_loop_rate_low"], table["metrics.closed_loop_rate"] - 0.01)
    assert list(table["metrics.xi_mean[1]"]) == [0.2] * 6 and list(table["job"]) == [0, 1, 2] * 2
    assert "params.plant.A" not in table        # matrices are not scalars
    grouped = table.groupby("params.enkf.q_scale")["metrics.closed_loop_rate"].mean()
    np.testing.assert_allclose(grouped.to_numpy(), [0.9, 0.92, 0.94])


@pytest.mark.parametrize("where, ids", [
    ("params.enkf.q_scale >= 1 and metrics.lam < 0.8115", ["A/1", "B/1"]),
    ("enkf.q_scale = 4 and closed_loop_status == 'failed'", ["A/2", "B/2"]),      # short names, `=`
    ("seed == 1 and lam > 0.815", ["B/2"]),
])
def test_search_where(root, where, ids):
    assert list(runs.search(root, where)["id"]) == ids


def test_bad_where_is_one_line(root):
    with pytest.raises(ValueError, match="where 'nosuch > 1'"):
        runs.search(root, "nosuch > 1")


def test_list_changed_sort_columns_csv(root, tmp_path):
    out = rdsexp("list", str(root), "--changed", "--sort=-closed_loop_rate", "--where", "seed == 0",
                 cwd=tmp_path, module="rdsexp.runs").stdout.splitlines()
    assert out[0].split() == ["id", "sweep", "plant", "plant_hash", "seed", "overrides", "status", "enkf.q_scale",
                              "lam", "closed_loop_rate"]
    assert [line.split()[0] for line in out[1:]] == ["A/2", "A/1", "A/0"]
    csv = rdsexp("list", str(root), "--columns", "enkf.q_scale,seed,lam", "--csv", cwd=tmp_path,
                 module="rdsexp.runs").stdout
    table = pd.read_csv(pd.io.common.StringIO(csv))
    assert list(table.columns) == ["params.enkf.q_scale", "seed", "metrics.lam"] and len(table) == 6
    both = rdsexp("list", str(root), "--columns", "lam", "--changed", "--csv", cwd=tmp_path, module="rdsexp.runs")
    assert list(pd.read_csv(pd.io.common.StringIO(both.stdout)).columns) == ["metrics.lam", *runs.changed(
        runs.search(root))]                                       # --columns and --changed, both honoured
    bad = rdsexp("list", str(root), "--sort", "nosuch", cwd=tmp_path, module="rdsexp.runs", check=False)
    assert bad.returncode == 2 and bad.stderr.strip() == "rdsexp-runs: 'nosuch' names no column"


def test_identity_names_the_sweep_plant_and_seed_of_every_run(tmp_path):
    """A `-m` sweep without `+sweep=NAME` is named by its sweeping overrides (multirun.yaml); a plant file
    without `name:` is named by its file, also as params.plant.name; the seed is a column."""
    a = fake_run(tmp_path, "S", 0, ["seed=3", "plant.name=null"], summary(0.8, 0.9) | {"plant": "lossy3"})
    info = json.loads((a / "run.json").read_text())
    info["sweep"]["name"], info["seed"] = None, {"root": 3}
    (a / "run.json").write_text(json.dumps(info))
    OmegaConf.save({"hydra": {"overrides": {"task": ["plant=lossy3", "enkf.ensemble_size=50,100", "seed=3",
                                                      "closed_loop.rate_window=[10,20]"]}}},
                   tmp_path / "S" / "multirun.yaml")
    row = runs.search(tmp_path).iloc[0]
    assert (row["sweep"], row["plant"], row["params.plant.name"], row["seed"]) == \
        ("enkf.ensemble_size=50,100", "lossy3", "lossy3", 3)
    assert list(runs.search(tmp_path, "plant.name == 'lossy3'")["id"]) == ["S/0"]


def test_a_reused_job_is_one_row_unless_copies_are_asked_for(tmp_path):
    fake_run(tmp_path, "A", 0, ["seed=0"], summary(0.8, 0.9))
    fake_run(tmp_path, "A", 1, ["seed=1"], summary(0.81, 0.91))
    copy = fake_run(tmp_path, "B", 0, ["seed=0"], summary(0.8, 0.9))     # B's job 0 reused A/0
    info = json.loads((copy / "run.json").read_text())
    (copy / "run.json").write_text(json.dumps(info | {"reused_from": "A/0"}))
    assert list(runs.search(tmp_path)["id"]) == ["A/0", "A/1"]                 # the original is kept
    assert runs.search(tmp_path)["metrics.lam"].mean() == pytest.approx(0.805)  # counted once
    assert list(runs.search(tmp_path, "sweep_id == 'B'")["reused_from"]) == ["A/0"]    # its sweep's row
    assert list(runs.search(tmp_path, copies=True)["id"]) == ["A/0", "A/1", "B/0"]


@pytest.mark.slow
def test_diff_runs_and_sweeps(root, tmp_path):
    rows = runs.diff(str(root / "A" / "0"), str(root / "A" / "2"))
    got = {(r.what, r.key): (r.a, r.b) for r in rows.itertuples()}
    assert got[("param", "enkf.q_scale")] == (0.25, 4.0) and got[("metric", "closed_loop_status")] == ("ok", "failed")
    assert ("metric", "seconds") not in got and ("param", "seed") not in got
    assert runs.diff(str(root / "A" / "1"), str(root / "A" / "1")).empty
    rows = runs.diff(str(root / "A"), str(root / "B"))
    got = {(r.what, r.key): (r.a, r.b) for r in rows.itertuples()}
    assert got[("param", "seed")] == (0, 1)
    assert got[("swept", "enkf.q_scale")] == ("0.25, 1.0, 4.0", "0.25, 1.0, 4.0")
    assert got[("metric", "lam @ enkf.q_scale=4.0")] == pytest.approx((0.82, 0.821))
    assert not any(k.startswith("closed_loop_rate") for _, k in got)      # equal in both sweeps
    out = rdsexp("diff", "A", "B", "--root", str(root), cwd=tmp_path, module="rdsexp.runs").stdout
    assert "lam @ enkf.q_scale=0.25" in out


def test_show_sweep(root, tmp_path):
    out = rdsexp("show", "B", "--root", str(root), cwd=tmp_path, module="rdsexp.runs").stdout.splitlines()
    assert out[0] == "sweep B: noise, 3 jobs (3 complete)"
    assert out[3].split() == ["job", "enkf.q_scale", "status", "lam", "closed_loop_rate", "closed_loop_failed_fraction",
                              "reused_from"]


def test_load_adds_run_id_and_long_form(small_run):
    wide = runs.load(small_run, "trajectories")
    info = json.loads((small_run / "run.json").read_text())
    assert wide["run"].eq(info["id"]).all() and list(wide.columns[:4]) == ["run", "experiment", "k", "path"]
    long = runs.load(small_run, "trajectories", long=True)
    assert list(long.columns) == ["run", "experiment", "path", "k", "quantity", "index", "value"]
    values = [c for c in wide.columns if "[" in c]
    assert len(long) == len(wide) * len(values)
    pick = long[(long["experiment"] == "closed_loop") & (long["path"] == 2) & (long["k"] == 7)
                & (long["quantity"] == "x_filt_mean") & (long["index"] == 3)]["value"]
    want = wide[(wide["experiment"] == "closed_loop") & (wide["path"] == 2) & (wide["k"] == 7)]["x_filt_mean[3]"]
    assert pick.tolist() == want.tolist()
    with pytest.raises(ValueError, match="not a trajectory table"):
        runs.load(small_run, "gains", long=True)
    with pytest.raises(ValueError, match="table 'nosuch'"):
        runs.load(small_run, "nosuch")


def test_tables_carry_run_id_and_described_columns(small_run):
    info = json.loads((small_run / "run.json").read_text())
    for name, meta in info["tables"].items():
        frame = pd.read_parquet(small_run / meta["file"])
        attrs = frame.attrs["rdsexp"]
        assert attrs["run"] == info["id"] and attrs["table"] == name
        assert list(attrs["columns"]) == list(frame.columns)
        missing = [c for c, d in attrs["columns"].items() if not d["description"]]
        assert not missing, (name, missing)
    gains = pd.read_parquet(small_run / "gains.parquet")
    m, n = 1, 6                                   # the paper's plant
    assert [c for c in gains.columns if c.startswith("F[")] == [f"F[0,{j}]" for j in range(n)][: m * n]
    paths = pd.read_parquet(small_run / "paths.parquet")
    assert paths.loc[paths["failed_at"] < 0, "failure"].isna().all()


def test_data_dictionary_in_docs_is_current():
    from conftest import REPO

    from rdsexp.experiment import schema
    assert (REPO / "docs" / "data_dictionary.md").read_text() == schema.markdown()


def test_sweep_recording_and_view(root, tmp_path, monkeypatch):
    """summary.rrd draws each metric against the swept value, a timeline of its own (a float key: a duration
    whose seconds are the values): per x the mean over the seeds (a line) and the runs (points)."""
    for name in ("DISPLAY", "WAYLAND_DISPLAY"):        # no display: `view` prints the command
        monkeypatch.delenv(name, raising=False)
    import rerun as rr

    from rdsexp.experiment.recording import read_series, write_sweep_recording
    path = write_sweep_recording(root / "A")
    assert path == root / "A" / "summary.rrd"
    table = runs.search(root / "A")
    q, lam = read_series(path, "/sweep/rates/lam/enkf.q_scale/all/mean", index="enkf.q_scale (1 s = 1)")
    assert (q / np.timedelta64(1, "s")).tolist() == [0.25, 1.0, 4.0] and lam.tolist() == table["metrics.lam"].tolist()
    # both sweeps as one: seeds 0 and 1 at each q_scale
    both = runs.search(root)
    (tmp_path / "AB").mkdir()
    path = write_sweep_recording(tmp_path / "AB", table=both)
    by_q = both.groupby("params.enkf.q_scale")
    for group, metric in (("rates", "closed_loop_rate"), ("rates", "lam"), ("fractions", "closed_loop_failed_fraction")):
        base = f"/sweep/{group}/{metric}/enkf.q_scale/all"
        q, mean = read_series(path, f"{base}/mean", index="enkf.q_scale (1 s = 1)")
        want = by_q[f"metrics.{metric}"].mean()
        assert (q / np.timedelta64(1, "s")).tolist() == want.index.tolist()
        np.testing.assert_allclose(mean, want.to_numpy(), rtol=1e-12)
        _, points = read_series(path, f"{base}/runs", index="enkf.q_scale (1 s = 1)")      # 2 runs per x
        np.testing.assert_allclose(np.sort(points.reshape(3, 2), axis=1),
                                   np.sort(np.stack(by_q[f"metrics.{metric}"].apply(np.asarray)), axis=1))
    jobs = rr.chunk.RrdReader(path).store().stream().filter(content=["/sweep/jobs"]).collect()
    text = jobs.reader(index=None, contents="/sweep/jobs").to_arrow_table()["/sweep/jobs:TextDocument:text"][0]
    text = text.as_py()[0]
    assert text.startswith("**sweep noise · plant paper**: 6 jobs") and "swept: **enkf.q_scale, seed**" in text
    assert text.count("| complete |") == 6 and "| 2 | complete | 4 | 1 | 0.821 | 0.94 [0.93, 0.95] | 0 |" in text
    out = rdsexp("view", "A", "--root", str(root), cwd=tmp_path, module="rdsexp.runs").stdout
    assert out.split()[-1] == str(root / "A" / "summary.rrd") and "rerun" in out.split()[0]


def test_sweep_recording_hues_and_axes(tmp_path):
    """Two numeric keys: two timelines, the other key and the non-numeric gain.method the hue; the seed alone:
    the x; nothing numeric: the job."""
    import rerun as rr

    from rdsexp.experiment.recording import read_series, write_sweep_recording
    rng = np.random.default_rng(0)
    grid = pd.MultiIndex.from_product([[20, 40], [0.5, 2.0], ["proposed", "lqr_mean"], [0, 1, 2]],
                                      names=["params.enkf.ensemble_size", "params.enkf.q_scale", "params.gain.method",
                                             "params.seed"]).to_frame(index=False)
    table = grid.assign(job=np.arange(len(grid)), sweep="grid", plant="paper", status="complete",
                        **{"metrics.lam": rng.uniform(0.8, 0.9, len(grid)),
                           "metrics.closed_loop_failed_fraction": rng.uniform(0, 1, len(grid))})
    table = table.sample(frac=1, random_state=1)            # the recording orders the rows by job itself
    path = write_sweep_recording(tmp_path, table=table)
    hue = rr.escape_entity_path_part
    for x, other, timeline in (("enkf.ensemble_size", "q_scale", "enkf.ensemble_size"),
                               ("enkf.q_scale", "ensemble_size", "enkf.q_scale (1 s = 1)")):
        means = table.groupby([f"params.enkf.{other}", "params.gain.method", f"params.{x}"])["metrics.lam"].mean()
        for (value, gain), want in means.groupby(level=[0, 1]):
            entity = f"/sweep/rates/lam/{x}/{hue(f'{other}={value:g}, method={gain}')}/mean"
            xs, mean = read_series(path, entity, index=timeline)
            if xs.dtype.kind == "m":
                xs = xs / np.timedelta64(1, "s")
            assert xs.tolist() == want.index.get_level_values(2).tolist()
            np.testing.assert_allclose(mean, want.to_numpy(), rtol=1e-12)
            other_timeline = "enkf.q_scale (1 s = 1)" if timeline == "enkf.ensemble_size" else "enkf.ensemble_size"
            with pytest.raises(ValueError, match="does not exist"):                 # on its own timeline only
                read_series(path, entity, index=other_timeline)
    _, fraction = read_series(path, f"/sweep/fractions/closed_loop_failed_fraction/enkf.q_scale/"
                              f"{hue('ensemble_size=40, method=lqr_mean')}/runs", index="enkf.q_scale (1 s = 1)")
    pick = table[(table["params.enkf.ensemble_size"] == 40) & (table["params.gain.method"] == "lqr_mean")]
    assert fraction.tolist() == pick.sort_values(["params.enkf.q_scale", "job"])[
        "metrics.closed_loop_failed_fraction"].tolist()
    seeds = table[(table["params.enkf.ensemble_size"] == 20) & (table["params.enkf.q_scale"] == 0.5)]
    write_sweep_recording(tmp_path, table=seeds)
    s, lam = read_series(tmp_path / "summary.rrd", f"/sweep/rates/lam/seed/{hue('method=proposed')}/mean", index="seed")
    assert s.tolist() == [0, 1, 2]
    assert lam.tolist() == seeds[seeds["params.gain.method"] == "proposed"].sort_values("job")["metrics.lam"].tolist()
    gains = seeds[seeds["params.seed"] == 0]
    write_sweep_recording(tmp_path, table=gains)
    jobs, lam = read_series(tmp_path / "summary.rrd", f"/sweep/rates/lam/job/{hue('method=lqr_mean')}/runs",
                            index="job")
    assert lam.tolist() == gains[gains["params.gain.method"] == "lqr_mean"]["metrics.lam"].tolist() and len(jobs) == 1


def test_rx_runs_is_the_catalog_imported_on_first_use():
    code = ("import sys, rdsexp as rx; light = 'pandas' not in sys.modules; "
            "import rdsexp.runs; assert rx.runs.load is rdsexp.runs.load and rx.runs.search; print(light)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert proc.stdout.strip() == "True"                   # `import rdsexp` alone stays free of pandas


def test_plot_a_sweep_from_the_command_line_and_from_python(root, tmp_path, capsys):
    """`rdsexp-runs plot SWEEP --x KEY --y METRIC`: the points table printed, the figure and its lineage written;
    rdsexp.runs.plot gives the same points from a --where selection."""
    rc = runs.main(["plot", "A", "--root", str(root), "--x", "enkf.q_scale", "--y", "closed_loop_rate",
                    "--out", str(tmp_path)])
    out = capsys.readouterr().out.splitlines()
    assert rc == 0 and out[0].split()[:3] == ["enkf.q_scale", "mean", "low"]
    assert [float(line.split()[0]) for line in out[1:4]] == [0.25, 1.0, 4.0]
    lineage = json.loads((tmp_path / "closed_loop_rate_vs_enkf.q_scale.json").read_text())
    assert sorted(r["id"] for r in lineage["runs"]) == ["A/0", "A/1", "A/2"]
    assert (tmp_path / "closed_loop_rate_vs_enkf.q_scale.png").stat().st_size > 0
    points, paths = runs.plot(x="q_scale", y="closed_loop_rate", where="sweep_id == 'A' or sweep_id == 'B'",
                              out=tmp_path / "both", root=root)
    assert list(points["n"]) == [2, 2, 2] and len(paths) == 5
    np.testing.assert_allclose(points["mean"], [0.9, 0.92, 0.94])


def test_show_a_run_names_its_identity_first(tmp_path, capsys):
    run = fake_run(tmp_path, "S", 1, ["seed=4"], summary(0.8, 0.9) | {"model": "paper"})
    info = json.loads((run / "run.json").read_text())
    (run / "run.json").write_text(json.dumps(info | {"seed": {"root": 4}, "overrides": ["seed=4"],
                                                     "reused_from": "T/0"}))
    assert runs.main(["show", "S/1", "--root", str(tmp_path)]) == 0
    assert capsys.readouterr().out.splitlines()[0] == \
        "run S/1: plant paper (model paper), sweep noise job 1, seed 4, overrides seed=4, reused from T/0"


def test_plot_needs_a_selection(root, capsys):
    assert runs.main(["plot", "--root", str(root), "--x", "q_scale", "--y", "lam"]) == 2
    assert capsys.readouterr().err.strip() == "rdsexp-runs: plot: name a SWEEP or give --where"


def test_help_of_every_command_prints_and_exits_0(capsys):
    """`rdsexp-runs --help` and each command's --help: argparse formats every help string (a bare % in
    one ended `--help` with a TypeError)."""
    with pytest.raises(SystemExit) as exit_:
        runs.main(["--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    commands = ["list", "check", "show", "verify", "view", "diff", *runs.COMMANDS]
    assert all(name in text for name in commands) and "95%" in text and "%%" not in text
    for name in commands:
        with pytest.raises(SystemExit) as exit_:
            runs.main([name, "--help"])
        assert exit_.value.code == 0 and capsys.readouterr().out.startswith("usage:"), name


LOSSY3 = """name: lossy3
A:
  - [[1.005, 0.10017], [0.10017, 1.005]]
  - [[0, 0], [0, 0]]
B:
  - [[0], [0]]
  - [[0.005], [0.10017]]
C:
  - [[1, 0]]
xi: {family: independent, components: [{family: bernoulli, prob: PROB}]}
"""


@pytest.mark.slow
def test_the_plant_content_is_part_of_a_runs_identity(tmp_path):
    """A plant file changed between two runs (one Bernoulli probability): run.json's plant_hash differs, the
    catalog and `show` carry it, `diff` names the hash and the changed entry inside the xi law's list; the
    hash is of the content (1 and 1.0, another file name and key order give the same one)."""
    from rdsexp.experiment.store import provenance
    conf = tmp_path / "conf" / "plant"
    conf.mkdir(parents=True)
    tiny = ["closed_loop.paths=2", "enkf.ensemble_size=10", "closed_loop.horizon=20", "tracking.recording=false",
            "closed_loop.open_loop=false", "identification.resamples=5"]
    dirs = []
    for prob in ("0.85", "0.9"):
        (conf / "lossy3.yaml").write_text(LOSSY3.replace("PROB", prob))
        rdsexp("--config-dir", "conf", "plant=lossy3", *tiny, cwd=tmp_path)
        dirs.append(max((tmp_path / "outputs" / "runs").iterdir(), key=lambda p: p.stat().st_mtime_ns))
    infos = [json.loads((d / "run.json").read_text()) for d in dirs]
    hashes = [i["plant_hash"] for i in infos]
    assert len(hashes[0]) == 64 and hashes[0] != hashes[1]
    table = runs.search(tmp_path / "outputs")
    assert sorted(table["plant_hash"]) == sorted(h[:12] for h in hashes)
    rows = runs.diff(str(dirs[0]), str(dirs[1]), root=tmp_path / "outputs")
    assert {"what": "plant_hash", "key": "plant_hash", "a": hashes[0][:12], "b": hashes[1][:12]} in \
        rows.to_dict("records")
    config = rows[rows["what"] == "config"]
    assert list(config["key"]) == ["plant.xi.components[0].prob"] and list(config["a"]) == [0.85]
    # the command pastes back from anywhere: with the absolute --config-dir
    assert infos[1]["command"].startswith(f"python -m rdsexp --config-dir {(tmp_path / 'conf').resolve()} plant=lossy3")
    shown = rdsexp("show", str(dirs[1]), cwd=tmp_path, module="rdsexp.runs").stdout.splitlines()[0]
    assert f"plant lossy3@{hashes[1][:6]} " in shown
    # `list --changed` compares inside lists too: the entry that tells the two plant files apart
    proc = rdsexp("list", "outputs", "--where", "plant == 'lossy3'", "--changed", "--csv", cwd=tmp_path,
                  module="rdsexp.runs")
    changed = pd.read_csv(io.StringIO(proc.stdout))
    assert sorted(changed["config.plant.xi.components[0].prob"]) == [0.85, 0.9]
    assert not [c for c in changed.columns if c.startswith("config.") and "prob" not in c]
    # no sweep has one spelling: "-" in `show`, in `list` and in a plot's title
    assert ", sweep -, seed" in shown
    listed = rdsexp("list", "outputs", "--columns", "sweep", cwd=tmp_path, module="rdsexp.runs").stdout.split()
    assert listed[listed.index("sweep") + 1:listed.index("sweep") + 3] == ["-", "-"]
    from rdsexp.report.sweep_plot import _title
    assert _title(SimpleNamespace(rows=table)).endswith("sweep -")
    one = provenance.plant_hash({"A": np.ones((1, 2, 2))}, {"family": "bernoulli", "prob": 1})
    assert one == provenance.plant_hash({"A": [[[1, 1], [1, 1.0]]]}, {"prob": 1.0, "family": "bernoulli"})
    assert one != provenance.plant_hash({"A": np.ones((1, 2, 2))}, {"family": "bernoulli", "prob": 0.999})


def test_diff_keeps_its_table_within_120_columns_with_long_texts_below():
    """`rdsexp-runs diff`: a verdict reason in a cell would widen the table to hundreds of columns; it is a note [n]
    there, written out in full below the table."""
    from rdsexp.experiment.catalog import diff_text
    reason = "the loop decays: the rate's 95% interval [0.9219, 0.9458] lies below 1 (k = 50..95) " * 3
    table = pd.DataFrame([{"what": "metric", "key": "closed_loop_verdict_reason", "a": reason, "b": "short"},
                          {"what": "metric", "key": "closed_loop_rate", "a": 0.93, "b": 0.94}])
    text = diff_text(table)
    head, notes = text.split("\n\n")
    assert all(len(line) <= 120 for line in head.splitlines()) and "[1]" in head and "short" in head
    assert notes == f"[1] a: {reason}"
