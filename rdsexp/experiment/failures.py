"""The one failure wrapper: an exception that ends a run becomes its status and exit code.

A numerical failure is never an exception (it is a status inside the tables); what reaches here is
a configuration the run cannot use, a store it cannot write, or a bug in a stage. The command line
records the status in run.json, prints `message` and exits with `exit_code`; a sweep records it
and goes on with the next job.

    ConfigError   config_error   exit 2   "<key>: <value> is not allowed, ..."
    DataError     config_error   exit 2   "data.file: <file>, row <n>, column <c>: ..." (labelled data error)
    WriteError    write_error    exit 1   "cannot write <path>: <reason>"
    StageError    error          exit 1   "stage <name>: <type>: <first line>", traceback kept
    other         error          exit 1   "stage run: <type>: <first line>", traceback kept
"""
from __future__ import annotations

import traceback
from dataclasses import dataclass

from ..errors import ConfigError, DataError, Exit, StageError, WriteError, one_line


@dataclass(frozen=True)
class Failure:
    """How a run ended when it did not complete: run.json's status and error message, the exit code
    of a single run and, for an unexpected error, the traceback (kept in run.json and the log)."""

    status: str
    exit_code: int
    message: str
    traceback: str | None = None
    label: str = ""             # the terminal line's label: config error, data error, or none

    @property
    def line(self) -> str:
        """The one line the terminal shows."""
        return f"rdsexp: {self.label + ': ' if self.label else ''}{self.message}"


def failure(err: Exception) -> Failure:
    """The Failure of an exception that ended a run (see the module's table)."""
    if isinstance(err, ConfigError):
        label = "data error" if isinstance(err, DataError) else "config error"
        return Failure("config_error", Exit.CONFIG, str(err), label=label)
    if isinstance(err, WriteError):
        return Failure("write_error", Exit.FAILED, str(err))
    trace = "".join(traceback.format_exception(err))
    if isinstance(err, StageError):
        return Failure("error", Exit.FAILED, str(err), trace)
    return Failure("error", Exit.FAILED, f"stage run: {one_line(err)}", trace)
