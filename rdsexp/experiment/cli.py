"""`rdsexp` / `python -m rdsexp`: the Hydra entry point, the only place that prints a run's outcome
and chooses the exit code.

One run: validate the config (exit 2 on a bad value, no run directory), compute and record it
(`runner.execute`), print its summary. A run that fails is recorded with its status (`failures`):
a single run exits 1 (2 for a config error), a sweep goes on with its next job.

The command line's own errors are one line on stderr too: a key no config has (`enkf.ensemble_sze=50`,
with the closest known key) and a YAML syntax error (file:line:column) exit 2 before any run or sweep
directory exists; Ctrl-C ends a run or sweep with exit 130 and one line saying what completed.
HYDRA_FULL_ERROR=1 shows the complete traceback instead.
"""
from __future__ import annotations

import contextlib
import logging
import os
import re
import shlex
import shutil
import signal
import sys
import warnings
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from ..errors import ConfigError, Exit, RunExit, WriteError, exit_codes_text, warnings_as_lines
from .store import layout

log = logging.getLogger("rdsexp")
CONF_PACKAGE = "pkg://rdsexp.conf"        # conf/ of the repository, shipped as the package rdsexp.conf
layout.register_resolvers()               # hydra.run.dir and hydra.sweep.dir (conf/config.yaml)
if not OmegaConf.has_resolver("rdsexp_exit_codes"):      # the exit codes in `rdsexp --help` (conf/hydra/help)
    OmegaConf.register_new_resolver("rdsexp_exit_codes", exit_codes_text)
RUNNING: dict[str, Path | None] = {}      # the run (and sweep) directory of the job started last, for Ctrl-C


STAGE_LINES = {"on": None}         # `main`'s choice: a line per stage on stderr (True), progress bars (False)


@hydra.main(config_path=CONF_PACKAGE, config_name="config", version_base="1.3")
def hydra_main(cfg: DictConfig) -> dict | float:
    """One job: its run.json content, or with `objective: METRIC` that metric as a float (what an
    optimizing sweeper such as Optuna's reads; `runner.objective_value`): its mean over `objective_seeds`
    seeds, the job's and the ones after it, each a run beside the job's (`runner.trial_seeds`)."""
    # imported here: `rdsexp --help` and shell completion need Hydra only, not the numerics
    from .pipeline.stage import announce_stages
    from .runner import execute, objective_over, objective_seeds, objective_value, trial_seeds
    from .store import write_sweep_summary
    from .summary import summary_text
    if STAGE_LINES["on"] is not None:    # this process ran `main` (a launcher's worker keeps the default: none)
        announce_stages(STAGE_LINES["on"])
    hc = HydraConfig.get()
    run_dir = Path(hc.runtime.output_dir)
    multirun = hc.mode == RunMode.MULTIRUN
    RUNNING.update(run_dir=run_dir, sweep_dir=Path(hc.sweep.dir) if multirun else None)
    amend = None
    try:
        if cfg.get("objective") and len(objective_seeds(cfg)) > 1:
            # a tuning trial's objective is its mean over objective_seeds seeds, with its standard error: its
            # other seeds run first, each a run beside this one, and the mean goes into this run's run.json
            others = trial_seeds(cfg, run_dir, lambda err, seed_dir: record_failure(
                err, cfg, seed_dir, job=hc.job.num if multirun else 0))
            penalty = float(cfg.get("objective_penalty", 1.0))
            amend = lambda info: info.update(objective=objective_over(                 # noqa: E731
                cfg.objective, penalty, [info, *others], objective_seeds(cfg), "trial"))
        info = execute(cfg, run_dir, amend=amend)
    except KeyboardInterrupt:             # run.json "interrupted", no temporary file, the sweep's summary agrees
        ignore_sigint()                   # a second Ctrl-C does not cut the record short
        from .store import settle_interrupted
        for stopped in [run_dir, *run_dir.parent.glob(f"{run_dir.name}.seed*")]:    # a trial's other seeds too
            settle_interrupted(stopped, wait=0)
        if multirun:
            with contextlib.suppress(WriteError):
                write_sweep_summary(Path(hc.sweep.dir))
        raise
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
            raise RunExit(Exit.FAILED)
    if cfg.get("objective"):
        trial = info.get("objective")            # over objective_seeds seeds (one seed: this run's value)
        return trial["mean"] if trial else objective_value(info, cfg.objective, float(cfg.get("objective_penalty",
                                                                                                  1.0)))
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
            with contextlib.suppress(OSError):           # and no empty runs/ (nor store) that Hydra made for it
                run_dir.parent.rmdir()
                run_dir.parent.parent.rmdir()
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


# Python's resource tracker (a process of its own under the joblib launcher and closed_loop.workers)
# removes the semaphores of worker queues a Ctrl-C abandoned and says so on stderr, 2 lines after the
# interrupt's one line: the removal stays, the lines go (the filter passes to every child by environment)
QUIET_TRACKER = "ignore::UserWarning:multiprocessing.resource_tracker"


def quiet_resource_tracker() -> None:
    """Add QUIET_TRACKER to PYTHONWARNINGS, for the processes this one starts."""
    current = os.environ.get("PYTHONWARNINGS", "")
    if QUIET_TRACKER not in current.split(","):
        os.environ["PYTHONWARNINGS"] = ",".join(filter(None, [current, QUIET_TRACKER]))


def main() -> None:
    """Console entry point `rdsexp` (and `python -m rdsexp`)."""
    try:
        _main()
    except BrokenPipeError:            # `rdsexp --help | head`: the reader stopped early, not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def _main() -> None:
    quiet_resource_tracker()
    # Ctrl-C stops a run or sweep even when the launching process ignored SIGINT (a child inherits
    # an ignored SIGINT): Python's default handler raises KeyboardInterrupt, which ends the run
    # with run.json "interrupted" (`hydra_main`) and every finished file complete
    signal.signal(signal.SIGINT, signal.default_int_handler)
    # a terminal has the progress bars; elsewhere, a line per stage (applied by hydra_main: importing the pipeline
    # here would cost `rdsexp --help` and every shell completion its 2.5 s)
    STAGE_LINES["on"] = not sys.stderr.isatty()
    for arg in sys.argv[1:]:
        # enkf.Q's default is the mapping {x, xi, matrix}: Hydra cannot merge a list into it and
        # would end with a stack of merge errors; say in one line where a matrix goes
        name, _, value = arg.partition("=")
        if name.lstrip("+") == "enkf.Q" and value.lstrip().startswith("["):
            print(f"rdsexp: config error: enkf.Q: {value} is not allowed, expected the scales enkf.Q.x=, "
                  f"enkf.Q.xi= or a matrix as enkf.Q.matrix={value} (a scalar, n+p diagonal entries or "
                  f"a full (n+p)x(n+p) matrix)", file=sys.stderr)
            sys.exit(Exit.CONFIG)
    # `data=FILE`: the data file of a data run, short for data.file=FILE (data is a mapping: file, holdout)
    sys.argv = [sys.argv[0], *(data_shorthand(arg) for arg in sys.argv[1:])]
    # a data run needs no plant: without one named, its plant group is `recorded` (no system, rdsexp's defaults
    # for a system of one's own) rather than the paper's, whose system the user's model need not match
    if any(arg.startswith("data.file=") for arg in sys.argv[1:]) and \
            not any(arg.lstrip("+~").startswith("plant=") for arg in sys.argv[1:]):
        sys.argv.append("plant=recorded")
    if {"--help", "-h"} & set(sys.argv[1:]):
        text = help_text(sys.argv[1:])
        if text is not None:
            print(text)
            return
    sys.argv = [sys.argv[0], *completion_config_dirs(sys.argv[1:], os.environ.get("COMP_LINE", "")), *sys.argv[1:]]
    # `rdsexp enkf.ensemble_size=50,100 -m b=2`: argparse takes the overrides as one run of arguments and
    # would refuse the ones after -m; -m takes no value, so it goes first
    multirun = [arg for arg in sys.argv[1:] if arg in ("-m", "--multirun")]
    sys.argv = [sys.argv[0], *multirun, *(arg for arg in sys.argv[1:] if arg not in multirun)]
    try:
        run_hydra_main()
    except RunExit as exit_:                 # rdsexp's own ending, with its exit code
        sys.exit(exit_.code)
    except SystemExit as exit_:
        # Hydra reports its own errors (a bad override, a missing config option, a key `+` cannot
        # add) and exits 1: a config error, exit 2
        if exit_.code == 1:
            print("rdsexp: config error (reported by Hydra above)", file=sys.stderr)
            sys.exit(Exit.CONFIG)
        raise


def data_shorthand(arg: str) -> str:
    """`data=FILE` (or `+data=FILE`) -> `data.file=FILE`; any other argument unchanged."""
    name, eq, value = arg.partition("=")
    if not eq or name.lstrip("+") != "data" or value.startswith("{"):
        return arg
    return f"data.file={os.path.abspath(value)}"       # absolute: `rdsexp-runs verify` re-runs from anywhere


# Hydra turns an exception of a callback into a warning and goes on: the sweep's validation
# (SweepSummary.on_multirun_start) must end the sweep before its directory exists
SWEEP_VALIDATION = r"Callback SweepSummary\.on_multirun_start raised"


def completion_config_dirs(argv: list[str], line: str) -> list[str]:
    """For shell completion (`-sc query=...`, the line being completed in COMP_LINE): the `--config-dir DIR`
    (or `-cd DIR`, `--config-dir=DIR`) of that line as arguments of this process, so that the options
    completed include the plant files and sweeps of DIR; [] otherwise."""
    if not any(a in ("-sc", "--shell-completion") or a.startswith("--shell-completion=") for a in argv) \
            or any(a in ("-cd", "--config-dir") or a.startswith("--config-dir=") for a in argv):
        return []
    try:
        words = shlex.split(line)
    except ValueError:                                   # an open quote in the line being typed
        words = line.split()
    found = []
    for i, word in enumerate(words):
        if word in ("-cd", "--config-dir") and i + 1 < len(words):
            found += ["--config-dir", os.path.expanduser(words[i + 1])]
        elif word.startswith("--config-dir="):
            found += ["--config-dir", os.path.expanduser(word.split("=", 1)[1])]
    return found


def run_hydra_main() -> None:
    """hydra_main, with Hydra's errors raised here instead of printed by Hydra (HYDRA_FULL_ERROR=1
    while it runs): a key no config has and a YAML syntax error end with one line (exit 2), Ctrl-C
    with one line saying what completed (exit 130). HYDRA_FULL_ERROR=1 set by the user: the traceback."""
    RUNNING.clear()                   # a Ctrl-C names this call's job, not one an earlier call in the process ran
    full_error = os.environ.get("HYDRA_FULL_ERROR")
    try:
        os.environ["HYDRA_FULL_ERROR"] = "1"
        try:
            with warnings_as_lines(), warnings.catch_warnings():
                warnings.filterwarnings("error", SWEEP_VALIDATION, UserWarning)
                hydra_main()
        finally:
            if full_error is None:
                del os.environ["HYDRA_FULL_ERROR"]
            else:
                os.environ["HYDRA_FULL_ERROR"] = full_error
    except (KeyboardInterrupt, Exception) as err:
        if full_error == "1":
            raise
        if interrupted_by(err):
            ignore_sigint()                               # a second Ctrl-C does not cut the line short
            print(f"rdsexp: {interrupted_text()}", file=sys.stderr)
            raise RunExit(Exit.INTERRUPTED) from None
        line = config_error_text(err)
        if line is None:
            hydra_report(err)                             # exits 1: "reported by Hydra above", exit 2
        print(f"rdsexp: config error: {line}", file=sys.stderr)
        raise RunExit(Exit.CONFIG) from None


def ignore_sigint() -> None:
    """Ignore further Ctrl-Cs (where this thread may set signal handlers)."""
    with contextlib.suppress(ValueError):                # not the main thread
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def interrupted_by(err: BaseException) -> bool:
    """err is a Ctrl-C, or an error raised while one was handled: Hydra's config reader, interrupted
    between opening a file and binding it, fails in its own cleanup (UnboundLocalError) with the
    KeyboardInterrupt as context."""
    seen = []
    while err is not None and err not in seen:
        if isinstance(err, KeyboardInterrupt):
            return True
        seen.append(err)
        err = err.__cause__ or err.__context__
    return False


def config_error_text(err: BaseException) -> str | None:
    """The one line of a config error Hydra raised (err or what it was raised from): a key no config
    has, a YAML syntax error; None for any other error."""
    import yaml
    from hydra.errors import ConfigCompositionException
    from omegaconf.errors import ConfigAttributeError, ConfigKeyError

    from .config import TOP_LEVEL
    chain = []
    while err is not None and err not in chain:
        chain.append(err)
        err = err.__cause__ or err.__context__
    for err in chain:
        if isinstance(err, ConfigError):    # raised inside Hydra's machinery (a sweeper's settings): its own line
            return str(err)
        if isinstance(err, yaml.MarkedYAMLError) and err.problem_mark is not None:
            return yaml_error_text(err)
        missing = re.match(r"In '[^']*': Could not find '([^'/]+)/([^']+)'\s+Available options in '[^']+':\s+(.*?)"
                           r"\s*Config search path", str(err), re.S)
        if missing:                     # a misspelled option of a group (plant=lossy, +sweep=seed)
            return missing_option_text(*missing.groups())
        cause = err.__cause__
        shadowed = re.match(r"Could not override '([^']+)'\. No match in the defaults list\.", str(err))
        if isinstance(err, ConfigCompositionException) and shadowed and shadowed.group(1) in (*TOP_LEVEL, "store"):
            # a directory of that name in a --config-dir is a config group to Hydra: `store=...` then
            # overrides a group that no default selects (e.g. a run store kept inside the config directory)
            return (f"{shadowed.group(1)}: a directory named {shadowed.group(1)!r} in the --config-dir is read "
                    f"by Hydra as a config group and hides the key {shadowed.group(1)}; move it out of the "
                    f"config directory")
        if isinstance(err, ConfigCompositionException) and isinstance(cause, (ConfigAttributeError, ConfigKeyError)):
            # "Could not override 'enkf.ensemble_sze'.\nTo append to your config use +enkf.ensemble_sze=50"
            name = re.search(r"override '([^']+)'", str(err))
            added = re.search(r"use (\+\S+)", str(err))
            if name and added and cause.parent_node is not None:
                return unknown_key_text(name.group(1), added.group(1), cause.parent_node._get_root())
    return None


def missing_option_text(group: str, option: str, listed: str) -> str:
    """`group=option` names no file of the group (Hydra lists the options it found, --config-dir ones
    included): one line with the closest options and all of them."""
    import difflib
    options = listed.split()
    close = difflib.get_close_matches(option, options, n=2, cutoff=0.5)
    parts = [f"{group}={option}: no such {group}"] + ([f"did you mean {' or '.join(close)}?"] if close else []) \
        + [f"options: {', '.join(options)}"]
    return "; ".join(parts)


def unknown_key_text(name: str, added: str, cfg) -> str:
    """`name=value` names a key the composed config `cfg` does not have: the closest known key
    (the check of `+key=value`, `config.check_overrides`), or how to add a key rdsexp reads."""
    from omegaconf import OmegaConf

    from .config import check_overrides
    try:                                  # rdsexp's keys only: hydra.* does not resolve before a job starts
        check_overrides(OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"]), [f"+{name}=null"])
    except ConfigError as err:            # "<name>: unknown key (added with +<name>), did you mean <key>?"
        hint = str(err).split(")", 1)[1].lstrip(",; ")
        return f"{name}: no such key; {hint}"
    except Exception:                     # noqa: BLE001 -- a config that does not resolve here: no hint
        return f"{name}: no such key"
    return f"{name}: not in the config; to add it, use {added}"


def yaml_error_text(err) -> str:
    """`file:line:column: problem (context at line, column)` of a YAML syntax error (1-based)."""
    mark = err.problem_mark
    text = f"{_shown(mark.name)}:{mark.line + 1}:{mark.column + 1}: {err.problem}"
    if err.context and err.context_mark is not None:
        where = "" if err.context_mark.name != mark.name else \
            f" at line {err.context_mark.line + 1}, column {err.context_mark.column + 1}"
        text += f" ({err.context}{where})"
    return text


def hydra_report(err: Exception) -> None:
    """Hydra's own report of an error rdsexp does not put in one line (as Hydra prints it without
    HYDRA_FULL_ERROR: its message, or a traceback for what is not one of Hydra's errors); exits 1."""
    from hydra._internal.utils import run_and_report

    def reraise():
        raise err
    run_and_report(reraise)


def interrupted_text() -> str:
    """What a Ctrl-C left behind, once settled (`store.settle_interrupted`: runs still "incomplete" whose
    process ended are "interrupted", the sweep's summary agrees with its jobs): the run, or the sweep's
    completed jobs (reused when the same command runs again)."""
    from omegaconf import OmegaConf

    from .store import settle_interrupted
    from .sweep import _SWEEP_BARS, sweep_points
    bar = _SWEEP_BARS.pop(os.getpid(), None)
    if bar is not None:
        bar.close()                                  # the bar's line ends before this one
    again = "run the same command again to resume: the completed jobs are reused"
    if not RUNNING:                                  # no job started here (or each in a launcher's worker)
        if bar is None:
            return "interrupted before the run started; nothing was recorded"
        if not bar.sweep_dir.is_dir():
            return f"interrupted: the sweep stopped; {again}"
        sweep_dir = bar.sweep_dir                    # the workers' jobs, counted from their run.json
    elif RUNNING["sweep_dir"] is None:
        run_dir = RUNNING["run_dir"]
        if _status(run_dir) != "interrupted":
            return "interrupted: the run stopped before it recorded anything; run the same command again to start it"
        return (f'interrupted: run {_shown(run_dir)} stopped, its run.json says "interrupted"; run the same '
                "command again to start it over")
    else:
        sweep_dir = RUNNING["sweep_dir"]
    with contextlib.suppress(OSError, WriteError):   # the count below reads what is there
        settle_interrupted(sweep_dir)
    done = sum(_status(job) == "complete" for job in sweep_dir.iterdir() if job.is_dir() and layout.is_job(job))
    try:
        config = OmegaConf.load(sweep_dir / layout.MULTIRUN)
        total, reuse = f" of {len(sweep_points(config))}", bool(config.get("reuse", True))
    except Exception:                                # noqa: BLE001 -- the count alone
        total, reuse = "", True
    if not reuse:
        again = "the same command runs every job again (reuse=false)"
    return f"interrupted: sweep {_shown(sweep_dir)} stopped with {done}{total} jobs completed; {again}"


def _status(run_dir: Path) -> str | None:
    """run.json's status in run_dir, None without a readable run.json."""
    from .store import status_of
    return status_of(run_dir)


def _shown(path) -> str:
    """A path as the terminal shows it: relative to the working directory when under it."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd().resolve()))
    except (ValueError, OSError):
        return str(path)


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
        "${hydra.help.footer}", help_cfg["footer"]).replace("$APP_CONFIG_GROUPS", listing).replace(
        "${rdsexp_exit_codes:}", exit_codes_text())
