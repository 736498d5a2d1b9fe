"""`python -m rdsexp [overrides]`: run the paper's experiment (or a sweep with +sweep=NAME)."""
from .experiment.cli import main

main()
