"""rdsexp's Hydra sweeper on Optuna (`hydra/sweeper: rdsexp_optuna`): trials by Optuna's ask-and-tell API."""
