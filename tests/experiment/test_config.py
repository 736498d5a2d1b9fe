"""Strict configs and exit codes: 0 ok, 1 error (or a sweep with failed jobs), 2 config error."""
import json
import sys

import pandas as pd
import pytest
from conftest import SERIAL, SMALL, rdsexp
from hydra import compose, initialize_config_module

from rdsexp.errors import ConfigError
from rdsexp.experiment.config import check_overrides

FAST = [*SMALL, "tracking.level=off"]


@pytest.mark.parametrize("override, message", [
    ("+enkf.ensemble_sze=50", "enkf.ensemble_sze: unknown key (added with +enkf.ensemble_sze), did you mean enkf.ensemble_size?"),
    ("++closed_loop.path=5", "closed_loop.path: unknown key (added with ++closed_loop.path), did you mean closed_loop.paths?"),
    ("+enkf.initial.meen=0", "enkf.initial.meen: unknown key (added with +enkf.initial.meen), did you mean enkf.initial.mean?"),
    ("+sed=3", "sed: unknown key (added with +sed), did you mean seed?"),
])
def test_unknown_added_key_is_one_line_with_a_suggestion(override, message):
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        cfg = compose("config", overrides=[override])
        with pytest.raises(ConfigError) as err:
            check_overrides(cfg, [override])
    assert str(err.value) == message


@pytest.mark.parametrize("override", ["+identification.xi_guess=[0.8,0.2]", "+gain.options.max_iter=3",
                                      "+sweep=seeds", "+plant.reference.rate_plant=0.8", "hydra.job.chdir=false"])
def test_keys_rdsexp_reads_may_be_added(override):
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        cfg = compose("config", overrides=[override] if not override.startswith("hydra") else [])
        check_overrides(cfg, [override])


@pytest.mark.parametrize("override, stderr", [
    ("+enkf.ensemble_sze=50", "did you mean enkf.ensemble_size?"),     # rdsexp's check
    ("+enkf.ensemble_size=50", "An item is already at 'enkf.ensemble_size'"),   # Hydra's own errors
    ("enkf=nosuch", "enkf=nosuch: no such enkf; options: etkf, paper"),
    ("enkf.ensemble_size=[", "no viable alternative"),
    ("closed_loop.observer_xi=walk", "closed_loop.observer_xi: 'walk' is not allowed, expected one of random_walk, model"),
    ("enkf.xi_support=clip", "enkf.xi_support: 'clip' is not allowed, expected one of project, free"),
    ("enkf.initial.xi=mean", "enkf.initial.xi: 'mean' is not allowed, expected one of guess, zero"),
    ("closed_loop.floor_paths=-1", "closed_loop.floor_paths: -1 is not allowed"),
    ("identification.xi_model=foo", "identification.xi_model: 'foo' is not allowed, expected one of random_walk, iterated"),
    ("identification.paths=0", "identification.paths: 0 is not allowed, expected an integer >= 1"),
    ("identification.passes=0", "identification.passes: 0 is not allowed, expected an integer >= 1"),
    ("identification.resamples=-1", "identification.resamples: -1 is not allowed, expected an integer >= 0"),
    ("identification.block=0", "identification.block: 0 is not allowed, expected an integer >= 1"),
    ("identification.covariance=full", "identification.covariance: 'full' is not allowed, expected one of sample, total"),
])
def test_config_errors_exit_2_whatever_raised_them(tmp_path, override, stderr):
    proc = rdsexp(override, *FAST, cwd=tmp_path, check=False)
    assert proc.returncode == 2, proc.stderr
    assert stderr in proc.stderr
    assert not (tmp_path / "outputs" / "runs").exists()      # not even an empty directory


def test_ok_run_exits_0(tmp_path):
    assert rdsexp(*FAST, cwd=tmp_path, check=False).returncode == 0


FAILING = """
import sys
import rdsexp.experiment.cli as cli
import rdsexp.experiment.runner as runner
real = runner.run_experiment
def failing(exp, *args, **kwargs):      # job seed=1 fails as an unforeseen error would
    if exp.seed == 1:
        raise RuntimeError("injected failure")
    return real(exp, *args, **kwargs)
runner.run_experiment = failing
sys.argv = ["rdsexp", *sys.argv[1:]]
cli.main()
"""


@pytest.mark.slow
def test_sweep_with_failed_job_writes_summary_and_exits_1(tmp_path):
    import subprocess
    script = tmp_path / "failing.py"
    script.write_text(FAILING)
    proc = subprocess.run([sys.executable, str(script), "+sweep=seeds", "seed=range(0,3)", *SMALL, SERIAL,
                           "tracking.recording=false", "model.reported=null"], cwd=tmp_path, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 1, proc.stderr
    assert "1 of 3 jobs did not complete (1 error)" in proc.stderr
    (sweep,) = (tmp_path / "outputs" / "sweeps").iterdir()
    summary = pd.read_parquet(sweep / "summary.parquet")
    assert list(summary["status"]) == ["complete", "error", "complete"]
    assert "injected failure" in json.loads((sweep / "1" / "run.json").read_text())["error"]


def test_auto_paths_look_at_four_times_the_previous_count_up_to_the_budget():
    """closed_loop.paths auto: looks from the pilot, each 4 times the last, the budget last (a last step of fewer
    than half the previous count merged into it); a fixed count is one look; the paper's plant keeps 200."""
    import numpy as np

    from rdsexp.experiment.config import LoopSettings, build
    settings = lambda paths, budget: LoopSettings(paths=paths, disturbance=np.zeros((2, 1)), filter_sees_disturbance=True,
                                                  open_loop=True, rate_window=None, floor_paths=20, observer_xi="model",
                                                  estimate="predicted", chunk_paths=None, workers=1, max_paths=budget)
    assert settings(50, 2000).looks == (50, 200, 800, 2000)
    assert settings(50, 1000).looks == (50, 200, 1000)
    assert settings(50, 50).looks == (50,)
    assert settings(30, None).looks == (30,)
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        assert build(compose("config", overrides=["plant=dropout"])).loop.looks == (50, 200, 800, 2000)
        assert build(compose("config")).loop.looks == (200,)
