"""The run store's layout: every file and folder name, defined once.

    <store>/                      DEFAULT_ROOT unless the config key `store` says otherwise
        runs/<stamp>_<uid>/       one run (RUN_DIR)
        sweeps/<stamp>_<uid>/     one sweep: multirun.yaml, summary.parquet (+ .csv), summary.rrd,
                                  resumes.json when it resumes an interrupted sweep
            <job>/                one job, a run directory like any other (named by its number); a tuning
                                  trial's other seeds <job>.seed<s>/ and a study's held-out re-runs
                                  heldout.seed<s>/ beside them
        index/                    the reuse index, one small JSON file per config hash and code version
        stages/<stage>/<key>/     the stage cache: one stage's result by the sha256 of what it is computed
                                  from (`stages`)
        quarantine/               damaged records moved aside by `rdsexp-runs check --quarantine`

A run directory holds RUN_JSON, Hydra's .hydra/ (HYDRA_CONFIG), one parquet file per table
(`table_file`), RECORDING, LOG and, when the working tree was dirty, DIFF. Hydra's run and sweep
directories are derived from this module through the resolvers `rdsexp_run_dir` and
`rdsexp_sweep_dir` (conf/config.yaml), registered by `register_resolvers`.
"""
from __future__ import annotations

import datetime as dt
import uuid
from pathlib import Path

DEFAULT_ROOT = "outputs"            # conf/config.yaml's `store` (a test checks they agree)
RUNS, SWEEPS, INDEX, QUARANTINE, STAGES = "runs", "sweeps", "index", "quarantine", "stages"

RUN_JSON = "run.json"
HYDRA_DIR = ".hydra"
HYDRA_CONFIG = f"{HYDRA_DIR}/config.yaml"
RECORDING = "recording.rrd"
FIGURE = "figure.png"                # the run's static figure (`experiment.figure`)
LOG = "rdsexp.log"
DIFF = "uncommitted.diff"

MULTIRUN = "multirun.yaml"           # written by Hydra into every sweep directory
RESUMES = "resumes.json"             # in a sweep that resumes an interrupted one: {"resumes": its id}
SUMMARY = "summary.parquet"
SUMMARY_CSV = "summary.csv"
SUMMARY_RECORDING = "summary.rrd"
SUMMARY_LOCK = ".summary.lock"
INDEX_BUILT = ".built"               # in index/: the index was built from a full scan of the store


def table_file(name: str) -> str:
    """The file of a run's table `name`."""
    return f"{name}.parquet"


def stage_entry(root: Path, stage: str, key: str) -> Path:
    """The stage cache's entry of `stage` under `key` in the store `root`."""
    return Path(root) / STAGES / stage / key


def is_run(directory: Path) -> bool:
    """Whether `directory` is a run directory (it has a run.json)."""
    return (Path(directory) / RUN_JSON).exists()


def is_job(directory: Path) -> bool:
    """Whether a directory of a sweep is one of its jobs (named by its number), not a tuning trial's other
    seed or a held-out re-run beside them."""
    return Path(directory).name.isdigit()


def is_sweep(directory: Path) -> bool:
    """Whether `directory` is a sweep directory (Hydra's multirun.yaml, or jobs with a run.json)."""
    directory = Path(directory)
    return directory.is_dir() and not is_run(directory) and (
        (directory / MULTIRUN).exists() or any(directory.glob(f"*/{RUN_JSON}")))


def _stamp() -> str:
    # unique even for directories made in the same microsecond
    return f"{dt.datetime.now():%Y-%m-%d_%H-%M-%S-%f}_{uuid.uuid4().hex[:8]}"


def register_resolvers() -> None:
    """OmegaConf resolvers for Hydra's `hydra.run.dir` and `hydra.sweep.dir`: `<store>/runs/<stamp>`
    and `<store>/sweeps/<stamp>`. Cached, so that every job of one sweep resolves the same directory."""
    from omegaconf import OmegaConf
    for name, folder in (("rdsexp_run_dir", RUNS), ("rdsexp_sweep_dir", SWEEPS)):
        if not OmegaConf.has_resolver(name):
            OmegaConf.register_new_resolver(name, lambda root, folder=folder: f"{root}/{folder}/{_stamp()}",
                                            use_cache=True)
