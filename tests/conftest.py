"""Shared helpers: a small, fast configuration of the paper's experiment and a CLI runner."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

# the paper's experiment shrunk to run in about a second
SMALL = ["closed_loop.paths=4", "enkf.ensemble_size=20", "closed_loop.horizon=30", "closed_loop.rate_window=[10,20]",
         "closed_loop.disturbance.until=10", "identification.horizon=30", "identification.K0=5",
         "identification.K1=20"]


def rdsexp(*args, cwd, module="rdsexp", check=True, timeout=600):
    """Run `python -m <module> args` in cwd; returns the CompletedProcess."""
    env = dict(os.environ, PYTHONWARNINGS="ignore::DeprecationWarning")
    proc = subprocess.run([sys.executable, "-m", module, *args], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout, env=env)
    if check and proc.returncode != 0:
        raise AssertionError(f"exit {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr}")
    return proc


@pytest.fixture(scope="session")
def small_run(tmp_path_factory):
    """One complete small run (tracking summary); returns its run directory."""
    cwd = tmp_path_factory.mktemp("run")
    rdsexp(*SMALL, cwd=cwd)
    (run_dir,) = (cwd / "outputs" / "runs").iterdir()
    return run_dir
