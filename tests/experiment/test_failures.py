"""Bad input, numerical failure and interruption never lose or mislabel a result."""
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pandas as pd
import pytest
from conftest import SERIAL, SMALL, rdsexp, serial
from hydra import compose, initialize_config_module

import rdsexp as rx
from rdsexp.errors import ConfigError
from rdsexp.experiment.config import build
from rdsexp.numerics.enkf import EnKF
from rdsexp.numerics.simulation import simulate

ROW6 = "[0,0,0,0,0,0]"
BAD_CONFIGS = [
    ("enkf.ensemble_size=1", "enkf.ensemble_size: 1 is not allowed, expected an integer >= 2"),
    ("enkf.ensemble_size=2.5", "enkf.ensemble_size: 2.5 is not allowed, expected an integer >= 2"),
    ("enkf.R=-0.01", "enkf.R: must be positive semidefinite"),
    ("enkf.R=[0.01,0.01]", "enkf.R: shape (2,) is not allowed, expected a scalar, 3 diagonal entries or (3, 3)"),
    ("enkf.Q.x=-1", "enkf.Q.x: -1 is not allowed, expected a finite number >= 0"),
    ("enkf.Q.xi=nan", "enkf.Q.xi: nan is not allowed"),
    ("enkf.Q.matrix=[1,2]", "enkf.Q.matrix: shape (2,) is not allowed, expected a scalar, 9 diagonal entries or (9, 9)"),
    ("enkf.Q.matrix=[[1,2],[3]]", "enkf.Q.matrix: [[1, 2], [3]] is not allowed, expected a scalar, 9 diagonal"),
    ("enkf.Q.matrix=abc", "enkf.Q.matrix: 'abc' is not allowed"),
    ("enkf.Q.matrix=-1", "enkf.Q.matrix: must be positive semidefinite"),
    ("+enkf.Q.y=1", "enkf.Q: {'x': 0.01, 'xi': 0.02, 'matrix': None, 'y': 1} is not allowed, expected {x: scale, xi"),
    ("enkf.q_scale=-1", "enkf.q_scale: -1 is not allowed, expected a finite number >= 0"),
    ("enkf.r_scale=inf", "enkf.r_scale: inf is not allowed"),
    ("enkf.initial.mean=[0,0]", "enkf.initial.mean: [0, 0] is not allowed, expected null or 9 finite numbers"),
    ("enkf.initial.cov=-1", "enkf.initial.cov: must be positive semidefinite"),
    ("identification.K1=95", "identification.K1: K0 + K1 = 115 is not allowed, must be <= identification.horizon = 100"),
    ("identification.K0=-1", "identification.K0: -1 is not allowed, expected an integer >= 0"),
    ("identification.horizon=-5", "identification.horizon: -5 is not allowed, expected an integer >= 1"),
    ("identification.input.register_length=40", "identification.input.register_length: 40 is not allowed"),
    ("identification.input.amplitude=0", "identification.input.amplitude: 0 is not allowed, expected a finite number > 0"),
    ("identification.input.levels=tri", "identification.input.levels: 'tri' is not allowed, expected one of bipolar"),
    ("identification.input.hold=0", "identification.input.hold: 0 is not allowed, expected an integer >= 1"),
    ("identification.input.taps=[9]", "identification.input: taps: [9], expected integers in 1..register_length-1"),
    ("identification.input.state=[0,0,0,0,0,0,0]", "identification.input: state: [0, 0, 0, 0, 0, 0, 0], expected 7 bits"),
    ("identification.input.seed=-3", "identification.input.seed: -3 is not allowed, expected an integer >= 0"),
    ("gain.source=magic", "gain.source: 'magic' is not allowed, expected one of identified, reported, fixed"),
    ("gain.source=fixed", "gain.F: None is not allowed with gain.source = fixed, expected an (m, n) = (1, 6)"),
    ("gain.source=fixed +gain.F=[[1,2]]", "gain.F: [[1, 2]] is not allowed with gain.source = fixed"),
    ("gain.method=magic", "gain.method: 'magic' is not allowed, expected one of proposed, nominal_lmi"),
    ("+gain.options.speed=2", "gain.options: proposed: unknown option(s) ['speed']"),
    ("gain=pole_placement gain.options.poles=[0.9,0.8]", "gain.options: poles: 2 given, the system has n = 6"),
    ("gain=pole_placement gain.options.poles=[1.5,0.8,0.7,0.6,0.5,0.4]", "gain.options: poles: [1.5, 0.8, 0.7, 0.6, 0.5, 0.4] must lie strictly inside the unit disc"),
    ("gain=pole_placement gain.options.poles=[0.5,0.5,0.7,0.6,0.4,0.3]", "gain.options: poles: multiplicity 2 exceeds the number of inputs m = 1"),
    ("gain=lqr_mean gain.options.input_weight=0", "gain.options: input_weight: 0 is not allowed, expected a number > 0"),
    ("gain.options.tol=-1", "gain.options: tol: -1 is not allowed, expected a number > 0"),
    ("closed_loop.paths=0", "closed_loop.paths: 0 is not allowed, expected an integer >= 1"),
    ("closed_loop.paths=many", "closed_loop.paths: 'many' is not allowed, expected auto or an integer >= 1"),
    ("closed_loop.paths=auto closed_loop.pilot_paths=1", "closed_loop.pilot_paths: 1 is not allowed, expected an integer >= 2"),
    ("closed_loop.paths=auto closed_loop.max_paths=20", "closed_loop.max_paths: 20 is not allowed, expected an integer >= 50"),
    ("closed_loop.horizon=-1", "closed_loop.horizon: -1 is not allowed, expected an integer >= 1"),
    ("closed_loop.rate_window=[80,60]", "closed_loop.rate_window: [80, 60] is not allowed"),
    ("closed_loop.rate_window=[60,200]", "closed_loop.rate_window: [60, 200] is not allowed"),
    ("closed_loop.disturbance.amplitude=nan", "closed_loop.disturbance.amplitude: nan is not allowed"),
    ("closed_loop.open_loop=maybe", "closed_loop.open_loop: 'maybe' is not allowed, expected true or false"),
    ("tracking.level=loud", "tracking.level: 'loud' is not allowed, expected one of off, summary, full"),
    ("seed=-3", "seed: -3 is not allowed, expected an integer >= 0"),
    ("plant.q0=[1,1,1]", "plant.q0: [1, 1, 1] is not allowed, expected null or 6 finite numbers"),
    ("plant.A=[[[1,2],[3]]]", "plant: A: expected a list of numeric matrices"),
    (f"plant.A=[[{ROW6},{ROW6}]]", "plant: A: basis matrices must be square"),
    ("plant.xi.cov=[[0.04,0],[0,-0.09]]", "plant.xi: cov: must be positive semidefinite"),
    ("plant.xi.mean=[0.8]", "plant.xi: cov: shape (2, 2) does not match mean of length 1"),
    ("model.B=[[[0],[0.4],[0]]]", "model: B: basis matrices have shape (3, 1), expected (6, 1)"),
    ("model.C=[[[1,0,0,0,0,0]]]", "model: (n, m, ny) = (6, 1, 1) does not match the plant's (6, 1, 3)"),
    ("model.reported.mean=[0.4,0.1]", "model.reported: cov: shape (3, 3) does not match mean of length 2"),
]


@pytest.fixture(autouse=True)
def hydra_context():
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        yield


@pytest.mark.parametrize("overrides, message", BAD_CONFIGS, ids=[c[0] for c in BAD_CONFIGS])
def test_bad_config_message(overrides, message):
    with pytest.raises(ConfigError) as err:
        build(compose("config", overrides=overrides.split()))
    assert str(err.value).startswith(message), str(err.value)
    assert "\n" not in str(err.value)


def test_bad_config_table_is_large():
    assert len(BAD_CONFIGS) >= 25


def test_bad_single_run_exits_2_without_run_directory(tmp_path):
    proc = rdsexp("closed_loop.paths=-2", cwd=tmp_path, check=False)
    assert proc.returncode == 2
    assert proc.stderr.strip() == ("rdsexp: config error: closed_loop.paths: -2 is not allowed, "
                                   "expected an integer >= 1")
    assert not (tmp_path / "outputs" / "runs").exists() or not any((tmp_path / "outputs" / "runs").iterdir())


def test_bad_sweep_point_fails_before_any_job(tmp_path):
    proc = rdsexp("+sweep=ensemble_size", "enkf.ensemble_size=10,1", "seed=0", *SMALL[:1], cwd=tmp_path, check=False)
    assert proc.returncode == 2
    assert "enkf.ensemble_size: 1 is not allowed" in proc.stderr
    assert not (tmp_path / "outputs").exists()


@pytest.mark.parametrize("call, message", [
    (lambda: rx.AffineRandomSystem(A=[np.eye(2)], B=[np.ones((2, 1))]).Gbar(rx.MomentModel([0.0], [[1.0]])),
     "dist: has dimension 1, the system has p = 0"),
    (lambda: rx.synthesize(rx.paper.model(), rx.MomentModel([0.0], [[1.0]])), "dist: has dimension 1"),
    (lambda: rx.ms_rate(rx.paper.model(), rx.paper.modeled_distribution(), np.ones((6, 1))), "F: shape (6, 1)"),
    (lambda: rx.ms_rate(rx.paper.model(), None, np.ones((1, 6))), "dist: no distribution of xi given"),
    (lambda: rx.MomentModel.from_samples(np.ones(3)), "xis: expected 2 dimensions"),
    (lambda: EnKF(rx.paper.model(), np.eye(9), np.eye(2)), "R: shape (2, 2) is not allowed, expected a scalar, 3 diagonal entries or (3, 3)"),
    (lambda: simulate(rx.paper.plant(), EnKF(rx.AffineRandomSystem(A=[np.eye(6)], B=[np.ones((6, 2))],
                                                                 C=[np.eye(3, 6)]), 0.01, 0.01),
                      d=np.zeros((5, 1)), q0=np.ones(6), psi0=np.zeros(6), ensemble_size=5, paths=1, seed=0),
     "plant: (n, m, ny) = (6, 1, 3) does not match the EnKF model's (6, 2, 3)"),
    (lambda: simulate(rx.paper.model(), EnKF(rx.paper.model(), 0.01, 0.01), d=np.zeros((5, 1)), q0=np.ones(6),
                      psi0=np.zeros(9), ensemble_size=5, paths=1, seed=0), "plant: needs xi_dist"),
    (lambda: rx.second_moments(rx.paper.plant(), None, rx.paper.F_proposed, np.ones(5), np.zeros((3, 1))),
     "x0: shape (5,)"),
])
def test_python_api_raises_clear_value_errors(call, message):
    with pytest.raises(ValueError) as err:
        call()
    assert message in str(err.value) and "\n" not in str(err.value)


@pytest.mark.slow
def test_diverging_run_is_recorded_as_a_status_without_warnings(tmp_path):
    # its own process: a warning would reach stderr there, not pytest's capture
    proc = rdsexp("gain=pole_placement", *SMALL, "closed_loop.horizon=60", cwd=tmp_path, process=True)
    assert "Warning" not in proc.stderr and "overflow" not in proc.stderr
    (run_dir,) = (tmp_path / "outputs" / "runs").iterdir()
    info = json.loads((run_dir / "run.json").read_text())
    assert info["status"] == "complete" and info["summary"]["closed_loop_status"] == "failed"
    paths = pd.read_parquet(run_dir / "paths.parquet")
    closed = paths[paths["experiment"] == "closed_loop"]
    assert (closed["failure"] == "diverged").all() and (closed["failed_at"] > 0).all()
    q = pd.read_parquet(run_dir / "trajectories.parquet").query("experiment == 'closed_loop' and k == 1")
    assert np.isfinite(q["q[0]"]).all()                                    # the finite part is kept


@pytest.mark.slow
def test_rerun_disabled_in_the_environment_gives_a_complete_run_without_recording(tmp_path, monkeypatch):
    """RERUN=off turns Rerun's streams off: the run (and a sweep of it) still completes, with every
    table and an intact record, only without recording.rrd."""
    monkeypatch.setenv("RERUN", "off")
    proc = rdsexp(*SMALL, "seed=0,1", "--multirun", cwd=tmp_path, process=True)   # Rerun warns on file 2
    assert "sweep recording: none (Rerun disabled" in proc.stdout and "WARN" not in proc.stderr
    runs = sorted(tmp_path.glob("outputs/sweeps/*/*/run.json"))
    assert len(runs) == 2
    for path in runs:
        info = json.loads(path.read_text())
        assert info["status"] == "complete" and "recording" not in info
        assert not (path.parent / "recording.rrd").exists() and (path.parent / "trajectories.parquet").exists()
    assert "no damaged or inconsistent record" in rdsexp("check", str(tmp_path / "outputs"), cwd=tmp_path,
                                                         module="rdsexp.runs").stdout


def wait_for(predicate, timeout=120.0):
    start = time.time()
    while not predicate():
        if time.time() - start > timeout:
            raise TimeoutError
        time.sleep(0.05)


def complete_jobs(root):
    return [p for p in root.glob("outputs/sweeps/*/*/run.json") if json.loads(p.read_text()).get("status") == "complete"]


@pytest.mark.slow
def test_killed_sweep_resumes_and_keeps_every_result(tmp_path):
    """Kill a sweep (SIGKILL: no handler runs) after its first job, relaunch the same command: completed jobs are
    reused (same config hash and code version), the rest run, the summary has every job. (Ctrl-C:
    tests/experiment/test_cli_errors.py.)"""
    args = ["+sweep=seeds", "seed=range(0,4)", *SMALL, "closed_loop.paths=40", "tracking.recording=false",
            "model.reported=null"]
    proc = subprocess.Popen([sys.executable, "-m", "rdsexp", *serial(args)], cwd=tmp_path,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wait_for(lambda: len(complete_jobs(tmp_path)) >= 1)      # then three jobs to go: time for the kill to arrive
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    done_before = {json.loads(p.read_text())["config_hash"] for p in complete_jobs(tmp_path)}
    assert 1 <= len(done_before) < 4
    for p in tmp_path.glob("outputs/sweeps/*/*/*.parquet"):                # no truncated table
        pd.read_parquet(p)
    rdsexp(*args, cwd=tmp_path)
    latest = max((tmp_path / "outputs" / "sweeps").iterdir())
    summary = pd.read_parquet(latest / "summary.parquet")
    assert list(summary["job"]) == list(range(4)) and set(summary["status"]) == {"complete"}
    infos = [json.loads((latest / str(j) / "run.json").read_text()) for j in range(4)]
    reused = {i["config_hash"] for i in infos if i.get("reused_from")}
    assert reused == done_before


@pytest.mark.slow
def test_killed_run_is_marked_incomplete(tmp_path):
    proc = subprocess.Popen([sys.executable, "-m", "rdsexp", "closed_loop.paths=400", "tracking.recording=false"],
                            cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wait_for(lambda: list(tmp_path.glob("outputs/runs/*/run.json")))
    time.sleep(1.0)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    (info_path,) = tmp_path.glob("outputs/runs/*/run.json")
    assert json.loads(info_path.read_text())["status"] == "incomplete"
    listing = rdsexp("list", str(tmp_path / "outputs"), cwd=tmp_path, module="rdsexp.runs").stdout
    assert "incomplete" in listing


@pytest.mark.slow
def test_concurrent_sweeps_do_not_collide(tmp_path):
    args = [sys.executable, "-m", "rdsexp", "+sweep=seeds", "seed=range(0,3)", *SMALL, "tracking.recording=false",
            "model.reported=null", "reuse=false", SERIAL]
    procs = [subprocess.Popen(args, cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE) for _ in range(2)]
    for p in procs:
        assert p.wait(timeout=300) == 0, p.stderr.read()
    sweeps = sorted((tmp_path / "outputs" / "sweeps").iterdir())
    assert len(sweeps) == 2
    for sweep in sweeps:
        summary = pd.read_parquet(sweep / "summary.parquet")
        assert list(summary["job"]) == [0, 1, 2] and set(summary["status"]) == {"complete"}


def test_failure_wrapper_maps_each_exception_to_a_status_and_an_exit_code(tmp_path):
    from rdsexp.errors import ConfigError, StageError, WriteError
    from rdsexp.experiment.failures import failure
    from rdsexp.experiment.pipeline import timed

    f = failure(ConfigError("enkf.ensemble_size: 1 is not allowed"))
    assert (f.status, f.exit_code, f.traceback) == ("config_error", 2, None)
    assert f.line == "rdsexp: config error: enkf.ensemble_size: 1 is not allowed"
    f = failure(WriteError(tmp_path / "run.json", OSError(28, "No space left on device")))
    assert (f.status, f.exit_code, f.line) == ("write_error", 1, f"rdsexp: cannot write {tmp_path / 'run.json'}: "
                                                                "No space left on device")
    with pytest.raises(StageError) as err:            # the innermost stage names the failure
        with timed({}, "closed_loop"), timed({}, "metrics"):
            raise ValueError("boom\nsecond line")
    f = failure(err.value)
    assert (f.status, f.exit_code, f.message) == ("error", 1, "stage metrics: ValueError: boom")
    assert "ValueError: boom" in f.traceback
    with pytest.raises(WriteError):                   # not a stage's failure: passes through unchanged
        with timed({}, "tables"):
            raise WriteError(tmp_path, OSError(30, "Read-only file system"))
    f = failure(KeyError("selected"))
    assert (f.status, f.exit_code, f.message) == ("error", 1, "stage run: KeyError: 'selected'")
