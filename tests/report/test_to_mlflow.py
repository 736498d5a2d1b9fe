"""rdsexp-runs export --mlflow: stored runs (a two-job sweep and a single run, computed here) on a real
MLflow tracking server (SQLite backend, artifacts in tmp, started by the test on a free local port):
params, metrics, curves, tags and artifacts of a run against its run.json and the runs table, the
sweep as a parent run, a second export that adds nothing, an interrupted export completed, errors."""
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from conftest import SMALL, rdsexp

mlflow = pytest.importorskip("mlflow")

from rdsexp import runs  # noqa: E402
from rdsexp.report import to_mlflow  # noqa: E402

SWEEP_SMALL = [o for o in SMALL if not o.startswith("enkf.ensemble_size=")]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """`mlflow server` on 127.0.0.1 at a free port (its own process group, ended at teardown); started
    first, so that it comes up while the store is computed."""
    directory = tmp_path_factory.mktemp("mlflow")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    log = open(directory / "server.log", "w")
    env = dict(os.environ, MLFLOW_SERVER_ENABLE_JOB_EXECUTION="false")     # no job runner processes
    proc = subprocess.Popen([sys.executable, "-m", "mlflow", "server", "--backend-store-uri",
                             f"sqlite:///{directory / 'mlflow.db'}", "--artifacts-destination",
                             str(directory / "artifacts"), "--host", "127.0.0.1", "--port", str(port), "--workers", "1"],
                            cwd=directory, stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    yield proc, f"http://127.0.0.1:{port}", directory / "server.log"
    os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    log.close()


@pytest.fixture(scope="module")
def store(server, tmp_path_factory):
    """A store: the sweep enkf.ensemble_size=20,40 (no recordings) and one single run with its recording."""
    cwd = tmp_path_factory.mktemp("store")
    rdsexp("-m", "enkf.ensemble_size=20,40", *SWEEP_SMALL, "tracking.recording=false", cwd=cwd)
    rdsexp(*SMALL, cwd=cwd)
    return cwd / "outputs"


@pytest.fixture(scope="module")
def uri(server, store):
    """The server's URI once it answers."""
    proc, uri, log = server
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"mlflow server exited {proc.returncode}:\n{log.read_text()[-3000:]}")
        try:
            with urllib.request.urlopen(f"{uri}/health", timeout=2) as answer:
                if answer.status == 200:
                    return uri
        except OSError:
            time.sleep(0.25)
    pytest.fail(f"mlflow server did not answer at {uri} within 180 s:\n{log.read_text()[-3000:]}")


@pytest.fixture(scope="module")
def exported(uri, store):
    """The whole store exported once to the default experiment: (report, client, runs table)."""
    table = runs.search(store)
    report = to_mlflow.export(table, uri)
    return report, mlflow.MlflowClient(uri), table


def mlflow_runs(client, experiment_id):
    return {r.info.run_id: r for r in client.search_runs([experiment_id], max_results=1000)}


@pytest.mark.slow
def test_each_run_with_its_params_metrics_curves_tags_and_artifacts(exported, tmp_path):
    report, client, table = exported
    assert sorted(report.exported) == sorted(table["id"]) and len(table) == 3 and not report.already
    assert report.lines()[0] == f"exported 3, already there 0: experiment 'rdsexp' (id {report.experiment_id}) at {report.uri}"
    assert client.get_experiment(report.experiment_id).name == "rdsexp"
    row = table[table["job"] == 1].iloc[0]                  # the job enkf.ensemble_size=40
    run = client.get_run(report.runs[row["id"]])
    run_dir = Path(row["dir"])
    info = json.loads((run_dir / "run.json").read_text())
    # params: the resolved config of run.json (the search table's params.*), as text
    assert run.data.params == {k: str(v) for k, v in info["params"].items()}
    assert run.data.params["enkf.ensemble_size"] == "40" == str(row["params.enkf.ensemble_size"])
    # metrics: every numeric metrics.* of the runs table at step 0 (xi_mean[0] named xi_mean.0), and the curves
    numeric = {k.removeprefix("metrics.").replace("[", ".").replace("]", ""): float(v) for k, v in row.items()
               if k.startswith("metrics.") and isinstance(v, (int, float, np.number)) and not isinstance(v, bool)
               and np.isfinite(v)}
    assert "closed_loop_rate" in numeric and "xi_mean.0" in numeric and "seconds" in numeric
    scalars = {k: v for k, v in run.data.metrics.items() if not k.startswith("rms/")}
    assert scalars == pytest.approx(numeric, rel=1e-12)
    assert {m.step for k in numeric for m in client.get_metric_history(run.info.run_id, k)} == {0}
    words = {f"summary.{k.removeprefix('metrics.')}": str(v) for k, v in row.items()
             if k.startswith("metrics.") and isinstance(v, (str, bool, np.bool_))}
    assert "summary.closed_loop_verdict" in words and "summary.loop_filter_sees_disturbance" in words
    assert {k: run.data.tags.get(k) for k in words} == words
    trajectories = runs.load(run_dir, "trajectories")
    for loop in ("closed_loop", "open_loop"):
        rows = trajectories[trajectories["experiment"] == loop]
        sq = (rows.filter(regex=r"^q\[").to_numpy() ** 2).sum(axis=1)
        by_k = {k: np.sqrt(np.mean(sq[(rows["k"] == k).to_numpy()])) for k in sorted(rows["k"].unique())}
        history = sorted(client.get_metric_history(run.info.run_id, f"rms/{loop}"), key=lambda m: m.step)
        assert [m.step for m in history] == list(by_k) == list(range(31))
        np.testing.assert_allclose([m.value for m in history], list(by_k.values()), rtol=1e-12)
        exact = runs.load(run_dir, "exact").query("experiment == @loop")
        history = sorted(client.get_metric_history(run.info.run_id, f"rms/{loop}_exact"), key=lambda m: m.step)
        assert [m.step for m in history] == exact["k"].tolist()
        np.testing.assert_allclose([m.value for m in history], exact["rms"], rtol=1e-12)
    # tags: identity of the run
    tags = run.data.tags
    assert {k: tags.get(f"rdsexp.{k}") for k in ("run_id", "code", "config_hash", "status", "plant", "sweep", "seed",
                                                 "sweep_id", "job")} == {
        "run_id": row["id"], "code": row["code"], "config_hash": row["config_hash"], "status": "complete",
        "plant": "paper", "sweep": "enkf.ensemble_size=20,40", "seed": str(row["seed"]), "sweep_id": row["sweep_id"],
        "job": "1"}
    assert tags["rdsexp.code"] == info["code"]["version"] and tags["rdsexp.config_hash"] == info["config_hash"]
    assert tags["mlflow.runName"] == "1 enkf.ensemble_size=40" and tags["rdsexp.export"] == "complete"
    assert "rdsexp.recording" not in tags                    # tracking.recording=false
    assert run.info.status == "FINISHED" and run.info.start_time == to_mlflow._millis(info["created"])
    # artifacts: run.json, the composed config and every stored table, byte for byte
    names = {f.path for f in client.list_artifacts(run.info.run_id)}
    assert names == {"run.json", "config.yaml", "plant.yaml", *(m["file"] for m in info["tables"].values())}
    assert tags["rdsexp.plant_hash"] == info["plant_hash"]                 # the plant's content, and the plant
    plant = yaml.safe_load(Path(client.download_artifacts(run.info.run_id, "plant.yaml", str(tmp_path))).read_text())
    assert plant == yaml.safe_load((run_dir / ".hydra" / "config.yaml").read_text())["plant"]
    assert {"trajectories.parquet", "exact.parquet", "metrics.parquet"} <= names
    for name in ("run.json", "metrics.parquet"):
        local = client.download_artifacts(run.info.run_id, name, str(tmp_path))
        assert Path(local).read_bytes() == (run_dir / name).read_bytes()


@pytest.mark.slow
def test_the_sweep_is_a_parent_run_and_a_single_run_is_top_level(exported):
    report, client, table = exported
    found = mlflow_runs(client, report.experiment_id)
    assert len(found) == 4                                          # the sweep's parent, its two jobs, the run
    (sweep_id,) = table["sweep_id"].dropna().unique()
    parent = found[report.parents[sweep_id]]
    assert parent.data.tags["rdsexp.kind"] == "sweep" and parent.data.tags["rdsexp.sweep_id"] == sweep_id
    assert parent.info.run_name == "enkf.ensemble_size=20,40" and parent.data.tags["rdsexp.swept"] == "enkf.ensemble_size"
    assert "mlflow.parentRunId" not in parent.data.tags
    assert [f.path for f in client.list_artifacts(parent.info.run_id)] == ["multirun.yaml"]
    jobs = table.loc[table["sweep_id"] == sweep_id, "dir"]            # the sweep's own times, not the export's
    assert parent.info.end_time == max(to_mlflow._millis(json.loads((Path(d) / "run.json").read_text())["finished"])
                                       for d in jobs)
    children = {r.data.tags["rdsexp.run_id"] for r in found.values()
                if r.data.tags.get("mlflow.parentRunId") == parent.info.run_id}
    assert children == set(table.loc[table["sweep_id"] == sweep_id, "id"])
    (single,) = table.loc[table["sweep_id"].isna()].itertuples()
    top = found[report.runs[single.id]]
    assert "mlflow.parentRunId" not in top.data.tags and top.info.run_name == single.id
    recording = Path(single.dir).resolve() / "recording.rrd"          # a link to the recording, not a copy
    assert recording.is_file() and top.data.tags["rdsexp.recording"] == str(recording)
    assert str(recording) in top.data.tags["mlflow.note.content"]
    assert "recording.rrd" not in {f.path for f in client.list_artifacts(top.info.run_id)}


@pytest.mark.slow
def test_a_second_export_adds_nothing(exported, store, capsys):
    report, client, _ = exported
    before = mlflow_runs(client, report.experiment_id)
    steps = len(client.get_metric_history(report.runs[report.exported[0]], "rms/closed_loop"))
    assert runs.main(["export", "--mlflow", report.uri, "--where", "status == 'complete'", "--root", str(store)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out == [f"exported 0, already there 3: experiment 'rdsexp' (id {report.experiment_id}) at {report.uri}",
                   f"{report.uri}/#/experiments/{report.experiment_id}/runs"]      # the runs table
    after = mlflow_runs(client, report.experiment_id)
    assert after.keys() == before.keys()
    assert all((a.data.params, a.data.metrics, a.data.tags) == (b.data.params, b.data.metrics, b.data.tags)
               for a, b in ((after[i], before[i]) for i in after))
    assert len(client.get_metric_history(report.runs[report.exported[0]], "rms/closed_loop")) == steps


@pytest.mark.slow
def test_an_interrupted_export_is_completed_with_what_it_lacks(uri, store):
    """A run created by an export that stopped part-way (some params, part of a curve, no artifacts, no
    tag rdsexp.export) gets the rest, each curve step once, and no second MLflow run."""
    (row,) = runs.search(store, "sweep_id != sweep_id").itertuples()       # the single run (no sweep)
    client = mlflow.MlflowClient(uri)
    experiment_id = client.create_experiment("interrupted")
    partial = client.create_run(experiment_id, tags={"rdsexp.run_id": row.id, "rdsexp.kind": "run"}).info.run_id
    client.log_batch(partial, params=[mlflow.entities.Param("seed", "0")],
                     metrics=[mlflow.entities.Metric("rms/closed_loop", 1.0, 0, k) for k in range(10)])
    report = to_mlflow.export(row.id, uri, "interrupted", root=store)
    assert report.completed == [row.id] and report.exported == [] and report.runs[row.id] == partial
    assert len(client.search_runs([experiment_id])) == 1
    run = client.get_run(partial)
    assert run.data.tags["rdsexp.export"] == "complete"
    assert run.data.params == {k: str(v) for k, v in json.loads((Path(row.dir) / "run.json").read_text())["params"].items()}
    assert sorted(m.step for m in client.get_metric_history(partial, "rms/closed_loop")) == list(range(31))
    assert "run.json" in {f.path for f in client.list_artifacts(partial)}
    again = to_mlflow.export(row.id, uri, "interrupted", root=store)
    assert again.already == [row.id] and not again.completed and not again.exported


@pytest.mark.slow
def test_failed_runs_are_exported_incomplete_and_damaged_ones_left_out(uri, store, tmp_path):
    """A run that ended in an error is exported with what it has (MLflow status FAILED); a run still being
    computed (status incomplete) and a run whose table was modified after it are named, not exported."""
    (row,) = runs.search(store, "sweep_id != sweep_id").itertuples()
    for name, status in (("failed", "error"), ("running", "incomplete"), ("damaged", "complete")):
        copy = tmp_path / "runs" / name
        shutil.copytree(row.dir, copy)
        for path in (copy / "run.json", copy / "metrics.parquet"):
            path.chmod(0o644)
        info = json.loads((copy / "run.json").read_text()) | {"id": name, "status": status}
        (copy / "run.json").write_text(json.dumps(info))
    (tmp_path / "runs" / "failed" / "trajectories.parquet").unlink()     # what a failed run may lack
    metrics = pd.read_parquet(tmp_path / "runs" / "damaged" / "metrics.parquet")
    metrics.assign(rate=metrics["rate"] * 0.5).to_parquet(tmp_path / "runs" / "damaged" / "metrics.parquet")
    report = to_mlflow.export(runs.search(tmp_path), uri, "left out")
    assert report.exported == ["failed"] and report.skipped == {
        "running": "incomplete (still running, or its process died)",
        "damaged": "damaged: metrics.parquet: modified after the run (does not match the hash in run.json)"}
    lines = report.lines()
    assert set(lines[:2]) == {f"left out {name}: {reason}" for name, reason in report.skipped.items()}
    assert lines[2] == f"exported 1, already there 0, left out 2: experiment 'left out' (id {report.experiment_id}) at {uri}"
    client = mlflow.MlflowClient(uri)
    failed = client.get_run(report.runs["failed"])
    assert failed.info.status == "FAILED" and failed.data.tags["rdsexp.status"] == "error"
    assert "rms/closed_loop" not in failed.data.metrics and "rms/closed_loop_exact" in failed.data.metrics
    names = {f.path for f in client.list_artifacts(failed.info.run_id)}
    assert "trajectories.parquet" not in names and {"run.json", "exact.parquet"} <= names


@pytest.mark.slow
def test_errors_in_one_line(store, capsys):
    assert runs.main(["export", "--mlflow", "http://127.0.0.1:9", "--root", str(store)]) == 2
    assert capsys.readouterr().err.strip() == "rdsexp-runs: export: name a SWEEP or RUN, or give --where"
    assert runs.main(["export", "--mlflow", "http://127.0.0.1:9", "--where", "seed == 0", "--root", str(store)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("rdsexp-runs: export: no MLflow tracking server answers at http://127.0.0.1:9 (")
    assert runs.main(["export", "--mlflow", "http://127.0.0.1:9", "--where", "seed == 7", "--root", str(store)]) == 2
    assert capsys.readouterr().err.strip() == "rdsexp-runs: export: no runs with seed == 7"


def test_mlflow_keys():
    assert to_mlflow.mlflow_key("xi_mean[0]") == "xi_mean.0" and to_mlflow.mlflow_key("F[0,1]") == "F.0.1"
    assert to_mlflow.mlflow_key("a b:c/d") == "a b:c/d" and to_mlflow.mlflow_key("what?") == "what_"
    long = to_mlflow.mlflow_key("k" * 300)
    assert len(long) == 250 and long != to_mlflow.mlflow_key("k" * 301)
    assert to_mlflow.mlflow_key("x", {"x": 1}) == "x~2"


@pytest.mark.slow
def test_reused_copies_add_no_mlflow_run_and_no_second_parent(uri, store):
    """The sweep command relaunched (every job a reused copy, a new sweep directory) and the single run's
    command run again: exported, they add no MLflow run and no parent; each copy is tagged on its
    original's run (one MLflow run per computation)."""
    client = mlflow.MlflowClient(uri)
    report = to_mlflow.export(runs.search(store), uri, "copies")
    before = mlflow_runs(client, report.experiment_id)
    assert len(before) == 4
    rdsexp("-m", "enkf.ensemble_size=20,40", *SWEEP_SMALL, "tracking.recording=false", cwd=store.parent)
    rdsexp(*SMALL, cwd=store.parent)
    copies = runs.search(store, "reused_from == reused_from", copies=True)
    assert len(copies) == 3
    sweep = Path(copies["dir"].dropna().iloc[0]).parent if copies["sweep_id"].notna().any() else None
    again = to_mlflow.export(str(sweep), uri, "copies", root=store)        # the relaunched sweep alone
    whole = to_mlflow.export(runs.search(store, copies=True), uri, "copies")
    after = mlflow_runs(client, report.experiment_id)
    assert after.keys() == before.keys() and not again.exported and not whole.exported
    assert not again.parents and sorted(whole.copies) == sorted(copies["id"])
    for copy in copies.itertuples():
        original = after[report.runs[copy.reused_from]]
        assert whole.runs[copy.id] == original.info.run_id
        assert original.data.tags[to_mlflow.mlflow_key(f"rdsexp.copy.{copy.id}")] == str(Path(copy.dir).resolve())
    assert "copies 3 (on their originals' runs)" in whole.lines()[0]


@pytest.mark.slow
def test_a_data_run_is_exported_with_its_data_file_as_identity(uri, tmp_path):
    """A data run (recorded data in place of a plant) on the real server: no plant hash, the data file's
    sha256 as its identity tag, its key numbers (exact rates on the identified model) as metrics."""
    example = Path(__file__).parents[2] / "examples" / "dropout"
    rdsexp("--config-dir", str(example), f"data={example / 'dropout.csv'}", "model=dropout", "plant=recorded",
           "data.holdout=0.2", "enkf.ensemble_size=20", "tracking=summary", cwd=tmp_path)
    store = tmp_path / "outputs"
    report = to_mlflow.export(str(next((store / "runs").iterdir())), uri, "data", root=store)
    (run_id,) = report.runs.values()
    run = mlflow.MlflowClient(uri).get_run(run_id)
    (info,) = [json.loads(p.read_text()) for p in (store / "runs").glob("*/run.json")]
    assert run.data.tags["rdsexp.data_sha256"] == info["data"]["sha256"] and "rdsexp.plant_hash" not in run.data.tags
    assert run.data.metrics["rate_model"] == info["summary"]["rate_model"]
    assert run.data.tags["summary.validation_modeled_better"] == str(info["summary"]["validation"]["modeled_better"])


@pytest.mark.slow
def test_a_directory_uri_is_one_line(store, capsys, tmp_path):
    """MLflow refuses to write a plain directory: the export says so in one line, exit 2."""
    assert runs.main(["export", "--mlflow", f"file://{tmp_path}/mlruns", "--where", "seed == 0",
                      "--root", str(store)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"rdsexp-runs: export: MLflow at file://{tmp_path}/mlruns: ") and "\n" not in err
