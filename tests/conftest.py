"""Shared helpers: a small, fast configuration of the paper's experiment and a CLI runner."""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import rdsexp as rx

REPO = Path(__file__).resolve().parent.parent

# the paper's experiment shrunk to run in about a second
SMALL = ["closed_loop.paths=4", "enkf.ensemble_size=20", "closed_loop.horizon=30", "closed_loop.rate_window=[10,20]",
         "closed_loop.disturbance.until=10", "identification.horizon=30", "identification.K0=5",
         "identification.K1=20", "tracking.figure=false"]     # the figure: tests/experiment/test_figure.py
# the shipped sweeps run their jobs in one worker process per core (conf/hydra/launcher/parallel.yaml);
# a test's sweeps of tiny jobs run one after the other in the process that launched them: no worker
# start-up per sweep (CI's time), an injected fault or a patch applies to every job, and a test's
# in-process sweep never meets a reused worker started in another test's working directory.
# tests/experiment/test_sweep.py runs the process launchers and checks their tables are the same.
SERIAL = "hydra/launcher=basic"


def serial(args) -> list:
    """args, with SERIAL added to a shipped sweep's (+sweep=NAME) unless they choose a launcher."""
    args = list(args)
    sweeps = any(str(a).startswith("+sweep=") for a in args)
    chosen = any(str(a).startswith(("hydra/launcher=", "hydra.launcher.")) for a in args)
    return [*args, SERIAL] if sweeps and not chosen else args


def rdsexp(*args, cwd, module="rdsexp", check=True, timeout=600, process=False):
    """`python -m <module> args` in cwd; returns a CompletedProcess. rdsexp and rdsexp.runs run in
    this process (their main() with sys.argv, cwd, stdout and stderr swapped: no interpreter start
    and imports per call); `process=True`, or any other module, in a fresh interpreter (what needs
    a process of its own: signals, environment variables, warnings printed on stderr)."""
    args = serial(args) if module == "rdsexp" else list(args)
    if process or module not in ("rdsexp", "rdsexp.runs"):
        env = dict(os.environ, PYTHONWARNINGS="ignore::DeprecationWarning")
        proc = subprocess.run([sys.executable, "-m", module, *args], cwd=cwd, capture_output=True, text=True,
                              timeout=timeout, env=env)
    else:
        proc = in_process(module, [str(a) for a in args], cwd)
    if check and proc.returncode != 0:
        raise AssertionError(f"exit {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr}")
    return proc


def rdsexp_each(calls) -> list:
    """Independent rdsexp calls, each (args, kwargs) as rdsexp(*args, **kwargs) takes them, two at a time
    (CI's two cores) in worker processes started once per test session (no interpreter start and imports
    per call, unlike `process=True`); their CompletedProcesses in the order given. A failed call raises its
    AssertionError here. Calls that share a store must be ones that may run at the same time (as two sweeps
    of one store may). The workers are started fresh, not forked: a fork of this process would inherit
    the solver's thread pool without its threads."""
    global _workers
    if _workers is None:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor
        _workers = ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn"))
    done = [_workers.submit(rdsexp, *args, **kwargs) for args, kwargs in calls]
    return [job.result() for job in done]


_workers = None


def pytest_sessionfinish(session):
    if _workers is not None:
        _workers.shutdown()


def in_process(module: str, args: list[str], cwd) -> subprocess.CompletedProcess:
    """Run the console entry point of `module` (rdsexp or rdsexp.runs) in this process."""
    import io
    import logging
    import signal
    from contextlib import redirect_stderr, redirect_stdout

    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.hydra_config import HydraConfig

    from rdsexp import runs
    from rdsexp.experiment import cli
    out, err, code = io.StringIO(), io.StringIO(), 0
    saved = os.getcwd(), sys.argv, signal.getsignal(signal.SIGINT)
    GlobalHydra.instance().clear()                    # a compose() a test left initialized
    try:
        os.chdir(cwd)
        sys.argv = [module, *args]
        with redirect_stdout(out), redirect_stderr(err):
            try:
                code = runs.main(args) if module == "rdsexp.runs" else cli.main()
            except SystemExit as exit_:
                if isinstance(exit_.code, str):        # sys.exit("message"): printed, exit code 1
                    print(exit_.code, file=sys.stderr)
                code = 1 if isinstance(exit_.code, str) else exit_.code or 0
    finally:
        os.chdir(saved[0])
        sys.argv = saved[1]
        signal.signal(signal.SIGINT, saved[2])
        GlobalHydra.instance().clear()
        HydraConfig.instance().cfg = None
        for name in (None, "rdsexp"):                 # the run's log file and the swapped stderr
            logger = logging.getLogger(name)
            for handler in list(logger.handlers):
                logger.removeHandler(handler)
                handler.close()
    return subprocess.CompletedProcess([module, *args], code or 0, out.getvalue(), err.getvalue())


@pytest.fixture(scope="session")
def small_run(tmp_path_factory):
    """One complete small run (tracking summary); returns its run directory."""
    cwd = tmp_path_factory.mktemp("run")
    rdsexp(*SMALL, cwd=cwd)
    (run_dir,) = (cwd / "outputs" / "runs").iterdir()
    return run_dir


def linear_gaussian(seed, n=3, ny=2):
    """A random linear system with known parameters (p = 0), y = C x, and a random R > 0: (system, C, R,
    the generator that drew them), for the EnKF variants' tests against the Kalman analysis."""
    rng = np.random.default_rng(seed)
    C = rng.normal(size=(ny, n))
    L = rng.normal(size=(ny, ny))
    R = L @ L.T + 0.1 * np.eye(ny)
    system = rx.AffineRandomSystem(A=[rng.normal(size=(n, n))], B=[np.zeros((n, 1))], C=[C])
    return system, C, R, rng


def undocumented(summary: dict) -> list[str]:
    """The keys of a run's summary that the data dictionary (`schema.RUN_SUMMARY_KEYS`) does not describe."""
    from rdsexp.experiment.schema import summary_entry
    return [key for key in summary if summary_entry(key) is None]


def import_source(node, package: str) -> str:
    """The absolute module an `ast.ImportFrom` node imports from: relative imports (`from .store import x`,
    level >= 1) resolved against `package`, the importing module's package."""
    base = package.rsplit(".", node.level - 1)[0] if node.level else ""
    return ".".join(p for p in (base, node.module) if p) if node.level else node.module or ""
