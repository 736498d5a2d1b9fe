"""Sweeps through other Hydra launchers: joblib workers, submitit (the Slurm code path,
run locally) and a local Ray cluster give the tables of the basic launcher, and the sweep summary
lists every job however many finish at once."""
import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from conftest import SMALL, rdsexp

SEEDS = "seed=0,1,2,3"                   # short jobs on two workers, so that some finish together
# what a launcher changes is where jobs run: no reported-moments designs, no recording (the tables
# still cover identification, every design on the identified moments and the closed loop)
TINY = [*SMALL, "closed_loop.open_loop=false", "model.reported=null", "tracking.recording=false"]


def sweep(tmp_path, name, *args, process=True):
    cwd = tmp_path / name
    cwd.mkdir()
    # a process of its own: a launcher leaves workers (and Ray a driver connection, which ends its
    # process when the cluster stops) behind in the process that launched the sweep; the basic
    # launcher leaves nothing and runs in this process
    rdsexp("-m", *args, *TINY, cwd=cwd, timeout=900, process=process)
    (sweep_dir,) = (cwd / "outputs" / "sweeps").iterdir()
    return sweep_dir


def table_hashes(sweep_dir: Path) -> dict:
    """{seed: {table: sha256}} of every job of a sweep."""
    out = {}
    for run_json in sweep_dir.glob("*/run.json"):
        info = json.loads(run_json.read_text())
        assert info["status"] == "complete", info.get("error")
        out[next(o for o in info["overrides"] if o.startswith("seed="))] = {k: v["sha256"] for k, v in info["tables"].items()}
    return out


@pytest.fixture(scope="module")
def basic(tmp_path_factory):
    return table_hashes(sweep(tmp_path_factory.mktemp("basic"), "basic", "hydra/launcher=basic", SEEDS, process=False))


@pytest.mark.slow
def test_joblib_workers_give_the_basic_tables_and_a_complete_summary(tmp_path, basic):
    sweep_dir = sweep(tmp_path, "joblib", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", SEEDS)
    assert table_hashes(sweep_dir) == basic
    summary = pd.read_parquet(sweep_dir / "summary.parquet")
    assert sorted(summary["job"]) == list(range(4)) and (summary["status"] == "complete").all()


@pytest.mark.slow
def test_submitit_local_gives_the_basic_tables(tmp_path, basic):
    # hydra/launcher=slurm uses the same submitit code path; submitit_local runs it without Slurm
    sweep_dir = sweep(tmp_path, "submitit", "hydra/launcher=submitit_local", "seed=0,1")
    hashes = table_hashes(sweep_dir)
    assert hashes == {k: basic[k] for k in hashes} and len(hashes) == 2


@pytest.mark.skipif(importlib.util.find_spec("hydra_plugins.hydra_ray_launcher") is None,
                    reason='needs the ray extra: pip install ".[ray]"')
@pytest.mark.slow
def test_ray_cluster_gives_the_basic_tables(tmp_path, basic):
    ray = shutil.which("ray", path=str(Path(sys.executable).parent)) or "ray"
    start = subprocess.run([ray, "start", "--head", "--num-cpus=2", "--include-dashboard=false",
                            "--disable-usage-stats"], capture_output=True, text=True, timeout=300)
    assert start.returncode == 0, start.stderr
    try:
        # the workers of a running cluster do not share this process's working directory: the sweep
        # directory is given as an absolute path (on a cluster: on a file system every node sees)
        sweep_dir = sweep(tmp_path, "ray", "hydra/launcher=ray_cluster", "hydra.launcher.ray.init.address=auto",
                          f"hydra.sweep.dir={tmp_path / 'ray' / 'outputs' / 'sweeps' / 'x'}",
                          "hydra.launcher.ray.remote.num_cpus=1", "seed=1")
    finally:
        subprocess.run([ray, "stop", "--force"], capture_output=True, timeout=300)
    # one job (the cost is the cluster and its worker's start): a seed other than the default, so the
    # override reached the worker; two jobs at once in other processes: joblib and submitit above
    assert table_hashes(sweep_dir) == {"seed=1": basic["seed=1"]}


def test_sweep_progress_counts_jobs_finished_in_other_processes_once(tmp_path):
    # joblib, Ray and Slurm run a job's callbacks in their workers: the launching process sees a job end
    # when its run.json leaves "incomplete"; a job it also sees end (basic launcher) counts once
    import io
    import time

    from rdsexp.experiment.sweep import SweepProgress
    for job, status in (("0", "complete"), ("1", "incomplete"), ("2", "failed")):
        (tmp_path / job).mkdir()
        (tmp_path / job / "run.json").write_text(json.dumps({"id": job, "status": status}))
    (tmp_path / "3").mkdir()                 # a job that has not written its run.json yet
    progress = SweepProgress(4, tmp_path, poll=0.02, file=io.StringIO(), disable=False)
    progress.finished("0")
    deadline = time.time() + 10
    while progress.bar.n < 2 and time.time() < deadline:
        time.sleep(0.02)
    time.sleep(0.1)
    assert progress.bar.n == 2 and progress.done == {"0", "2"}
    (tmp_path / "1" / "run.json").write_text(json.dumps({"id": "1", "status": "complete"}))
    while progress.bar.n < 3 and time.time() < deadline:
        time.sleep(0.02)
    progress.close()
    assert progress.bar.n == 3
    progress.finished("3")                   # after close: nothing counts any more
    assert progress.bar.n == 3
