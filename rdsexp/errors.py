"""rdsexp's exception types and the one-line form of any exception.

Errors are for what must stop before or outside the computation (a bad configuration, a store that
cannot be written or read); a numerical outcome (divergence, an infeasible LMI, a method that does
not apply) is a status in a result, never an exception (docs/design.md). Every message is one line
that names the thing (config key, file) and the reason, so that the command line can print it as
it is. The command line maps each type to its exit code (`rdsexp.experiment.failures`); the exit
codes themselves are `Exit`, in one place.
"""
from __future__ import annotations

import enum
import sys
import warnings
from contextlib import contextmanager
from pathlib import Path


def one_line(err: BaseException, with_type: bool = True) -> str:
    """An exception as one line: its type (unless `with_type` is False) and its message's first line."""
    lines = str(err).strip().splitlines()
    text = lines[0] if lines else ""
    if not with_type:
        return text or type(err).__name__
    return f"{type(err).__name__}: {text}".rstrip(": ")


class ConfigError(ValueError):
    """A configuration value that rdsexp cannot run with (one line: key, value, what is allowed)."""


class DataError(ConfigError):
    """A data file a data run cannot use (one line: file, row as a spreadsheet counts it, column, what is wrong):
    a configuration error of the data, labelled so."""


class WriteError(RuntimeError):
    """A write to the run store failed (disk full, permission denied, read-only file system)."""

    def __init__(self, path: Path, err: BaseException):
        reason = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
        super().__init__(f"cannot write {path}: {reason}")
        self.path = Path(path)


class DamagedRecord(Exception):
    """A stored record that cannot be read as written (one line: path and reason)."""

    def __init__(self, path: Path, reason: str):
        super().__init__(f"{path}: {reason}")
        self.path, self.reason = Path(path), reason


class RecordWarning(UserWarning):
    """A stored record skipped or ignored by a reader of the store (it goes on with the others)."""


@contextmanager
def warnings_as_lines():
    """Within: every RecordWarning is printed, each time, as the one line "rdsexp: warning: <message>"
    on stderr (the command line's form; the library only warns)."""
    with warnings.catch_warnings():
        warnings.simplefilter("always", RecordWarning)
        show = warnings.showwarning

        def one_line_record(message, category, *args, **kwargs):
            if issubclass(category, RecordWarning):
                print(f"rdsexp: warning: {message}", file=sys.stderr)
            else:
                show(message, category, *args, **kwargs)
        warnings.showwarning = one_line_record
        yield


class LineageError(RuntimeError):
    """Runs that must not be mixed (different code versions), tables that changed after the run, or
    no stored runs where a report script needs them."""


class StageError(RuntimeError):
    """An unexpected exception inside a stage of a run (`cause`), with the innermost stage's name."""

    def __init__(self, stage: str, cause: BaseException):
        super().__init__(f"stage {stage}: {one_line(cause)}")
        self.stage, self.cause = stage, cause


class Exit(enum.IntEnum):
    """The exit codes of `rdsexp`, each with what it means (`rdsexp --help` lists them from here)."""

    OK = 0
    FAILED = 1
    CONFIG = 2
    INTERRUPTED = 130

    @property
    def meaning(self) -> str:
        return {Exit.OK: "the run, or every job of the sweep, completed",
                Exit.FAILED: "a run or a job did not complete (its status and error are in its run.json), or the "
                             "store cannot be written",
                Exit.CONFIG: "a configuration error: nothing ran and nothing was recorded",
                Exit.INTERRUPTED: "Ctrl-C: the runs it stopped are recorded as interrupted; the same command "
                                  "resumes a sweep"}[self]


def exit_codes_text() -> str:
    """The exit codes and their meanings, a line each (for `rdsexp --help`)."""
    return "\n".join(f"{int(code):3d}  {code.meaning}" for code in Exit)


class RunExit(SystemExit):
    """The command line ends with this `Exit` code: after the run or sweep has started (FAILED), before
    it with a configuration error (CONFIG; any other exit of Hydra's is one too), or at a Ctrl-C
    (INTERRUPTED)."""
