"""`rdsexp` / `python -m rdsexp`: the Hydra entry point, the only place that prints a run's outcome
and chooses the exit code.

One run: validate the config (exit 2 on a bad value, no run directory), compute and record it
(`runner.execute`), print its summary. A run that fails is recorded with its status (`failures`):
a single run exits 1 (2 for a config error), a sweep goes on with its next job.
"""
from __future__ import annotations

import logging
import shutil
import signal
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from ..errors import RunExit, WriteError, warnings_as_lines
from .store import layout

log = logging.getLogger("rdsexp")
CONF_PACKAGE = "pkg://rdsexp.conf"        # conf/ of the repository, shipped as the package rdsexp.conf
layout.register_resolvers()               # hydra.run.dir and hydra.sweep.dir (conf/config.yaml)


@hydra.main(config_path=CONF_PACKAGE, config_name="config", version_base="1.3")
def hydra_main(cfg: DictConfig) -> dict:
    # imported here: `rdsexp --help` and shell completion need Hydra only, not the numerics
    from .runner import execute
    from .store import write_sweep_summary
    from .summary import summary_text
    hc = HydraConfig.get()
    run_dir = Path(hc.runtime.output_dir)
    multirun = hc.mode == RunMode.MULTIRUN
    try:
        info = execute(cfg, run_dir)
    except Exception as err:              # noqa: BLE001 -- every failure becomes a recorded status
        info = record_failure(err, cfg, run_dir, job=hc.job.num if multirun else None)
    if multirun:
        try:
            write_sweep_summary(Path(hc.sweep.dir))
        except WriteError as err:                         # the sweep's end writes it again, and fails loudly
            log.error("job %s: %s", hc.job.num, err)
    else:
        print(summary_text(info, run_dir))
        if info.get("status") != "complete":
            raise RunExit(1)
    return info


def record_failure(err: Exception, cfg: DictConfig, run_dir: Path, job: int | None) -> dict:
    """Record the failure of a run in its run.json and log it; a single run's config error leaves no
    run directory and ends at once (exit 2), a write error ends with its one line (exit 1)."""
    from .failures import failure
    from .store import RunWriter
    f = failure(err)
    if job is None and f.status in ("config_error", "write_error"):
        if f.status == "config_error":                   # nothing that could pass for a result
            shutil.rmtree(run_dir, ignore_errors=True)
        else:
            RunWriter(run_dir).fail(f.status, f.message, fallback=_fallback(cfg))
        print(f.line, file=sys.stderr)
        raise RunExit(f.exit_code)
    log.error("%s failed: %s", "run" if job is None else f"job {job}", f.message)
    if f.traceback:
        log.info("traceback:\n%s", f.traceback)        # rdsexp.log only (the terminal gets warnings and up)
    return RunWriter(run_dir).fail(f.status, f.message, f.traceback, fallback=_fallback(cfg))


def _fallback(cfg: DictConfig) -> dict:
    """What run.json records of a run that failed before its provenance was written."""
    from .runner import job_config
    from .store import provenance
    return {"config_hash": provenance.config_hash(job_config(cfg))}


def main() -> None:
    """Console entry point `rdsexp` (and `python -m rdsexp`)."""
    # Ctrl-C stops a run or sweep even when the launching process ignored SIGINT (a child inherits
    # an ignored SIGINT): Python's default handler raises KeyboardInterrupt, which ends the run
    # with run.json still "incomplete" and every finished file complete
    signal.signal(signal.SIGINT, signal.default_int_handler)
    for arg in sys.argv[1:]:
        # enkf.Q's default is the mapping {x, xi, matrix}: Hydra cannot merge a list into it and
        # would end with a stack of merge errors; say in one line where a matrix goes
        name, _, value = arg.partition("=")
        if name.lstrip("+") == "enkf.Q" and value.lstrip().startswith("["):
            print(f"rdsexp: config error: enkf.Q: {value} is not allowed, expected the scales enkf.Q.x=, "
                  f"enkf.Q.xi= or a matrix as enkf.Q.matrix={value} (a scalar, n+p diagonal entries or "
                  f"a full (n+p)x(n+p) matrix)", file=sys.stderr)
            sys.exit(2)
    if {"--help", "-h"} & set(sys.argv[1:]):
        text = help_text(sys.argv[1:])
        if text is not None:
            print(text)
            return
    try:
        with warnings_as_lines():
            hydra_main()
    except RunExit as exit_:                 # rdsexp's own ending, with its exit code
        sys.exit(exit_.code)
    except SystemExit as exit_:
        # Hydra reports its own errors (a bad override, a missing config option, a key `+` cannot
        # add) and exits 1: a config error, exit 2
        if exit_.code == 1:
            print("rdsexp: config error (reported by Hydra above)", file=sys.stderr)
            sys.exit(2)
        raise


def help_text(argv: list[str]) -> str | None:
    """`rdsexp --help` without composing a config: Hydra's help template (conf/hydra/help/rdsexp.yaml)
    with the config groups and options read from the installed configs and any `--config-dir`.
    Hydra's own help builds a config repository per group (seconds); this reads file names. None
    where another search path is given (`hydra.searchpath=...`): then Hydra prints it."""
    from importlib.resources import as_file, files

    import yaml
    if any(arg.lstrip("+").startswith("hydra.searchpath") for arg in argv):
        return None
    dirs = [arg.split("=", 1)[1] if "=" in arg else argv[i + 1] for i, arg in enumerate(argv)
            if arg.startswith(("--config-dir", "-cd")) and ("=" in arg or i + 1 < len(argv))]
    with as_file(files("rdsexp.conf")) as conf:
        groups: dict[str, set[str]] = {}
        for root in [Path(conf), *map(Path, dirs)]:
            for path in root.rglob("*.yaml"):
                group = path.parent.relative_to(root).as_posix()
                if group != "." and not group.startswith("hydra"):
                    groups.setdefault(group, set()).add(path.stem)
        help_cfg = yaml.safe_load((Path(conf) / "hydra" / "help" / "rdsexp.yaml").read_text())
    listing = "".join(f"{group}: {', '.join(sorted(options))}\n" for group, options in sorted(groups.items()))
    return help_cfg["template"].replace("${hydra.help.header}", help_cfg["header"]).replace(
        "${hydra.help.footer}", help_cfg["footer"]).replace("$APP_CONFIG_GROUPS", listing)
