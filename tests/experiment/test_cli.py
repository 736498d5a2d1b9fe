"""Runner, configs, sweeps, recordings and the run catalog, end to end."""
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import REPO, SMALL, rdsexp
from hydra import compose, initialize_config_module
from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import OmegaConf

import rdsexp as rx
from rdsexp.experiment import pipeline
from rdsexp.experiment.config import ConfigError, build
from rdsexp.experiment.recording import read_recording
from rdsexp.experiment.sweep import compose_points, enumerable, validate_sweep

SWEEPS = sorted(p.stem for p in (REPO / "conf" / "sweep").glob("*.yaml"))
GROUPS = {g: sorted(p.stem for p in (REPO / "conf" / g).glob("*.yaml"))
          for g in ("plant", "model", "enkf", "identification", "gain", "closed_loop", "tracking")}


@pytest.fixture(autouse=True)
def hydra_context():
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        yield


@pytest.mark.parametrize("group, option", [(g, o) for g, opts in GROUPS.items() for o in opts])
def test_every_config_option_composes_and_validates(group, option):
    """plant=recorded is a data run's plant group (no system): composed with the shipped example's data."""
    data = [f"data.file={REPO / 'docs' / 'data' / 'sample.csv'}", f"hydra.searchpath=[file://{REPO / 'examples' / 'dropout'}]",
            "model=dropout"] if (group, option) == ("plant", "recorded") else []
    build(compose("config", overrides=[f"{group}={option}", *data]))


def sweep_points(top):
    """The override lists of every job of the sweep whose config (with its hydra node) is `top`."""
    args = [f"{k}={v}" for k, v in top.hydra.sweeper.params.items()]
    return BasicSweeper.split_arguments(OverridesParser.create().parse_overrides(args), max_batch_size=None)[0]


@pytest.mark.parametrize("sweep", SWEEPS)
@pytest.mark.slow
def test_every_sweep_point_composes_and_validates(sweep):
    top = compose("config", overrides=[f"+sweep={sweep}"], return_hydra_config=True)
    if not enumerable(top):
        validate_sweep([[f"+sweep={sweep}"]])   # an optimizing sweeper's trials: each validated by its job
        return
    points = [[f"+sweep={sweep}", *overrides] for overrides in sweep_points(top)]
    assert len(points) >= 3
    validate_sweep(points)                # what a sweep runs first; exit 2 on the first bad point


@pytest.mark.parametrize("sweep", SWEEPS)
@pytest.mark.slow
def test_shipped_sweeps_use_every_core_unless_told_serial(sweep):
    """A shipped sweep's jobs run in one joblib worker per core; hydra/launcher=basic runs them one after
    the other. An optimizing sweeper's (tune_enkf: seeded, one trial after the other) stays serial."""
    def composed(*overrides):
        return compose("config", overrides=[f"+sweep={sweep}", *overrides], return_hydra_config=True)
    top = composed()
    default = top.hydra.launcher
    if enumerable(top):
        assert default._target_.endswith("JoblibLauncher") and default.n_jobs == -1
    else:
        assert default._target_.endswith("BasicLauncher")
    assert composed("hydra/launcher=basic").hydra.launcher._target_.endswith("BasicLauncher")


@pytest.mark.slow
def test_composing_once_per_group_choice_equals_a_full_compose():
    """The sweep validation's shortcut (group choices composed once, value overrides applied on top)
    gives every job exactly Hydra's config, for group and value overrides of every kind mixed."""
    points = [["+sweep=gain_methods", "gain=robust_box", "gain.options.width=0.5", "seed=3"],
              ["+sweep=gain_methods", "gain=proposed", "seed=4", "enkf.ensemble_size=20"],
              ["plant=dropout", "enkf.Q.x=2.0", "+tracking.note=hello", "closed_loop.paths=7"],
              ["plant=dropout", "~closed_loop.open_loop", "identification.K1=30"],
              ["controller=online", "controller.period=5", "seed=1"]]
    got = list(compose_points(points))
    assert len(got) == len(points)
    for overrides, cfg in got:
        assert OmegaConf.to_container(cfg) == OmegaConf.to_container(compose("config", overrides=overrides))
    # one working copy per group choice and keys, each point's values overwriting the last's
    shared = [["+sweep=gain_methods", "gain=proposed", f"seed={s}", f"enkf.ensemble_size={m}"]
              for s, m in ((1, 20), (2, 30), (3, 40))] + [["+sweep=gain_methods", "gain=proposed", "seed=9"]]
    for overrides, cfg in compose_points(shared, reuse=True):
        assert OmegaConf.to_container(cfg) == OmegaConf.to_container(compose("config", overrides=overrides))


def test_yaml_plant_and_model_are_the_papers():
    cfg = compose("config")
    exp = build(cfg)
    for got, want in ((exp.plant, rx.paper.plant()), (exp.model, rx.paper.model())):
        for name in "ABCD":
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    np.testing.assert_array_equal(exp.plant.xi_dist.cov, rx.paper.plant().xi_dist.cov)
    np.testing.assert_array_equal(exp.filter.enkf.Q, rx.paper.Q)
    np.testing.assert_array_equal(exp.loop.disturbance, rx.paper.disturbance())


def test_run_directory_contents(small_run):
    info = json.loads((small_run / "run.json").read_text())
    assert info["status"] == "complete"
    assert set(info["tables"]) == set(pipeline.TABLES)
    for key in ("config_hash", "code", "seed", "environment", "timings", "summary"):
        assert info[key]
    assert info["seed"]["root"] == 0 and info["environment"]["packages"]["rerun-sdk"].startswith("0.41")
    # the params `rdsexp-runs list` shows are those of the stored config, read without it
    from rdsexp.experiment.store.run import scalar_config
    from rdsexp.experiment.store.table import flat_params
    assert info["params"] == flat_params(scalar_config(small_run)) and info["params"]["enkf.ensemble_size"] == 20
    traj = pd.read_parquet(small_run / "trajectories.parquet")
    assert set(traj["experiment"]) == {"closed_loop", "open_loop"}
    assert len(traj) == 2 * 31 * 4 and {"q[5]", "x_pred_mean[0]", "xi_filt_std[2]", "u[0]"} <= set(traj.columns)
    gains = pd.read_parquet(small_run / "gains.parquet")
    # the paper's plant: the loop's method and the designs its Sec. V-B compares (plant.designs), on both moments
    assert list(gains["method"]) == ["proposed", "nominal_lmi", "pole_placement"] * 2 and gains["selected"].sum() == 1


def test_recording_equals_parquet_tables(small_run):
    """The .rrd read back with Rerun's own reader equals the identification + trajectory tables
    (stored path-major, recorded step by step)."""
    stored = pd.concat([pd.read_parquet(small_run / "identification.parquet"),
                        pd.read_parquet(small_run / "trajectories.parquet")], ignore_index=True)
    order = stored["experiment"].map({e: i for i, e in enumerate(stored["experiment"].unique())})
    stored = stored.assign(_e=order).sort_values(["_e", "k", "path"], kind="stable").drop(columns="_e")
    stored = stored.reset_index(drop=True)
    recorded = read_recording(small_run / "recording.rrd")
    pd.testing.assert_frame_equal(recorded, stored, check_dtype=False)


def test_verify_passes_on_fresh_run_and_fails_on_tampered_table(small_run, tmp_path):
    proc = rdsexp("verify", str(small_run), cwd=tmp_path, module="rdsexp.runs")
    assert "verify: identical" in proc.stdout
    tampered = tmp_path / "tampered"
    shutil.copytree(small_run, tampered)
    table = pd.read_parquet(tampered / "metrics.parquet")
    table.loc[0, "rate"] += 1e-9
    (tampered / "metrics.parquet").chmod(0o644)           # stored read-only: an edit is deliberate
    table.to_parquet(tampered / "metrics.parquet", index=False)
    proc = rdsexp("verify", str(tampered), cwd=tmp_path, module="rdsexp.runs", check=False)
    assert proc.returncode == 1
    assert "metrics" in proc.stdout and "rate: max |difference| 1e-09, first at row 0" in proc.stdout


def test_same_config_and_seed_give_identical_tables(small_run, tmp_path):
    rdsexp(*SMALL, cwd=tmp_path)
    (again,) = (tmp_path / "outputs" / "runs").iterdir()
    a, b = (json.loads((d / "run.json").read_text()) for d in (small_run, again))
    assert a["config_hash"] == b["config_hash"]
    assert {k: v["sha256"] for k, v in a["tables"].items()} == {k: v["sha256"] for k, v in b["tables"].items()}


def test_catalog_lists_runs(small_run, tmp_path):
    proc = rdsexp("list", str(small_run.parent), cwd=tmp_path, module="rdsexp.runs")
    assert small_run.name in proc.stdout and "complete" in proc.stdout


def sweep_tables(sweep_dir: Path):
    summary = pd.read_parquet(sweep_dir / "summary.parquet")
    return summary, {int(j): json.loads((sweep_dir / str(j) / "run.json").read_text())["tables"]
                     for j in summary["job"]}


@pytest.mark.slow
def test_sweep_end_to_end_designs_every_method(tmp_path):
    """+sweep=NAME with command-line overrides: one job per method, all complete (launcher
    independence of the tables: tests/experiment/test_sweep.py)."""
    rdsexp("+sweep=gain_methods", "seed=0", "tracking.recording=false", *SMALL, cwd=tmp_path)
    (sweep_dir,) = (tmp_path / "outputs" / "sweeps").iterdir()
    summary, tables = sweep_tables(sweep_dir)
    assert list(summary["job"]) == list(range(len(rx.synthesis.METHODS)))
    assert set(summary["status"]) == {"complete"}
    assert set(summary["method"]) == set(rx.synthesis.METHODS)
    assert all(set(t) == set(pipeline.TABLES) for t in tables.values())


@pytest.mark.parametrize("override, message", [
    ("enkf.ensemble_size=1", "enkf.ensemble_size: 1 is not allowed, expected an integer >= 2"),
    ("identification.K1=95", "identification.K1: K0 + K1 = 115 is not allowed"),
    ("gain.method=magic", "gain.method: 'magic' is not allowed"),
    ("enkf.R=-1", "enkf.R: must be positive semidefinite"),
    ("closed_loop.paths=0", "closed_loop.paths: 0 is not allowed"),
])
def test_bad_config_fails_with_one_line_and_no_run_directory(tmp_path, override, message):
    proc = rdsexp(override, cwd=tmp_path, check=False)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1] == f"rdsexp: config error: {message}" or message in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert not list((tmp_path / "outputs" / "runs").glob("*")) if (tmp_path / "outputs").exists() else True


def test_the_paper_keeps_its_loop_and_other_plants_get_theirs():
    """The paper's plant file keeps the paper's closed loop (unknown d_k, xi random walk, members at 0,
    u_k = F x_{k|k-1}, k = 60..80); every other plant defaults to the scenario measured on random plants."""
    paper = build(compose("config"))
    assert (paper.loop.filter_sees_disturbance, paper.loop.observer_xi, paper.loop.rate_window) == \
        (False, "random_walk", (60, 80))
    assert paper.loop.estimate == "predicted"
    assert not paper.filter.psi0.any()
    for name in ("dropout", "two_carts"):
        exp = build(compose("config", overrides=[f"plant={name}"]))
        assert (exp.loop.filter_sees_disturbance, exp.loop.observer_xi, exp.loop.rate_window) == (True, "model", None)
        assert exp.loop.estimate == "filtered"                     # auto: no D in these plants
        np.testing.assert_array_equal(exp.filter.psi0[exp.model.n:], exp.identification.xi_guess)   # model = plant
    # each stays selectable
    exp = build(compose("config", overrides=["plant=dropout", "closed_loop.observer_xi=random_walk",
                                             "closed_loop.filter_sees_disturbance=false", "enkf.initial.xi=zero",
                                             "closed_loop.estimate=predicted"]))
    assert (exp.loop.filter_sees_disturbance, exp.loop.observer_xi, exp.filter.psi0.any(), exp.loop.estimate) == \
        (False, "random_walk", False, "predicted")


@pytest.mark.parametrize("overrides, message", [
    (["closed_loop.estimate=current"], "closed_loop.estimate: 'current' is not allowed, expected auto or one of"),
    (["plant.D=[[[0.1],[0],[0]]]", "closed_loop.estimate=filtered"], "closed_loop.estimate: 'filtered' needs D = 0"),
])
def test_the_feedback_estimate_is_checked_before_any_work(overrides, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        build(compose("config", overrides=overrides))


def test_auto_estimate_is_the_prediction_when_the_output_depends_on_the_input():
    exp = build(compose("config", overrides=["plant=dropout", "plant.D=[[[0.1]]]"]))
    assert exp.loop.estimate == "predicted"


@pytest.mark.slow
def test_the_same_command_twice_reuses_the_stored_run(tmp_path):
    """A single run, like a sweep's job, is reused when the store holds one of the same config and code
    version: the second records a copy naming it, says so on its first line, and computes nothing."""
    args = ["closed_loop.paths=2", "enkf.ensemble_size=10", "closed_loop.horizon=20", "tracking.recording=false"]
    first = rdsexp(*args, cwd=tmp_path)
    second = rdsexp(*args, cwd=tmp_path)
    one, two = sorted((tmp_path / "outputs" / "runs").iterdir())
    info = json.loads((two / "run.json").read_text())
    assert info["reused_from"] == one.name and "reused" not in first.stdout.splitlines()[0]
    assert second.stdout.splitlines()[0].endswith(f"(reused run {one.name}: the same config and code version, "
                                                  f"nothing computed)")
    assert info["tables"] == json.loads((one / "run.json").read_text())["tables"]
    rdsexp(*args, "reuse=false", cwd=tmp_path)                  # reuse=false computes again
    assert len(list((tmp_path / "outputs" / "runs").iterdir())) == 3


@pytest.mark.slow
def test_a_sweep_that_records_nothing_says_so_in_one_line(tmp_path):
    proc = rdsexp("-m", "seed=1,2", "tracking=off", "closed_loop.paths=2", "enkf.ensemble_size=10",
                  "closed_loop.horizon=20", "hydra/launcher=basic", cwd=tmp_path)
    assert "sweep recording: none (no job recorded a run: tracking.level=off)" in proc.stdout
    assert "ZeroDivisionError" not in proc.stderr and "no sweep recording" not in proc.stderr


@pytest.mark.slow
def test_a_m_sweep_is_found_by_the_name_list_shows(tmp_path, capsys):
    """A sweep launched with -m and no +sweep=NAME is named by its swept overrides in `list`; `show` and
    `plot` find it by that name."""
    from rdsexp import runs
    rdsexp("-m", "seed=1,2", *SMALL, "tracking=summary", "hydra/launcher=basic", cwd=tmp_path)
    root = str(tmp_path / "outputs")
    capsys.readouterr()
    assert runs.main(["list", root, "--columns", "sweep"]) == 0
    assert set(capsys.readouterr().out.split()[1:]) >= {"seed=1,2"}
    assert runs.main(["show", "seed=1,2", "--root", root]) == 0
    out = capsys.readouterr().out
    assert out.startswith("sweep ") and "2 jobs (2 complete)" in out
    assert runs.main(["plot", "seed=1,2", "--x", "seed", "--y", "closed_loop_rate", "--root", root]) == 0
    assert list((tmp_path / "outputs" / "sweeps").glob("*/closed_loop_rate_vs_seed.png"))


@pytest.mark.parametrize("module", ["rdsexp", "rdsexp.runs"])
def test_output_into_a_reader_that_stopped_is_no_traceback(module):
    """`rdsexp --help | head`: standard output whose reader is gone (every write fails: EPIPE) ends without a
    BrokenPipeError traceback, exit 0."""
    read, write = os.pipe()
    os.close(read)
    try:
        proc = subprocess.run([sys.executable, "-m", module, "--help"], stdout=write, stderr=subprocess.PIPE,
                              text=True, timeout=120)
    finally:
        os.close(write)
    assert proc.stderr == "" and proc.returncode == 0


def test_a_run_whose_stderr_is_no_terminal_prints_a_line_per_stage(tmp_path):
    """Without a terminal (no progress bars), each outer stage says on stderr that it is done and in how long, in
    order; the summary with its verdicts stays on stdout."""
    proc = rdsexp(*SMALL, "tracking=off", cwd=tmp_path)
    lines = [line for line in proc.stderr.splitlines() if line.startswith("rdsexp: ")]
    stages = [line.split(": ", 1)[1].rsplit(" done in ", 1)[0] for line in lines]
    assert stages[:3] == ["identification", "noise sensitivity", "synthesis"] and "closed loop" in stages
    assert all(re.fullmatch(r"rdsexp: [a-z ]+ done in \d+\.\d s", line) for line in lines)
    assert "closed loop rate" in proc.stdout and "done in" not in proc.stdout
