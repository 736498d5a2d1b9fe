"""The run catalog as a public module: `rdsexp-runs ...` or `python -m rdsexp.runs ...` (see rdsexp.experiment.runs)."""
import sys

from .experiment.runs import *  # noqa: F403
from .experiment.runs import __all__, main  # noqa: F401

if __name__ == "__main__":
    sys.exit(main())
