"""A Hydra sweeper on current Optuna (ask and tell): `hydra/sweeper: rdsexp_optuna` (conf/sweep/tune_enkf.yaml).

Each trial is one job of the launcher, its value the job's return value (rdsexp's objective, `runner.objective_value`:
a float, inf for a failed run). The search space is Hydra's override grammar, in `hydra.sweeper.params` or on the
command line: `interval(a, b)` a float, `tag(log, interval(a, b))` on a log scale, `int(interval(a, b))` an integer,
`choice(...)` a category, a plain value fixed. The study (`storage`, `study_name`; SQLite: `optuna-dashboard
sqlite:///SWEEP/study.db` shows it) is created or resumed, the sampler (TPE, or random) seeded, `n_jobs` trials
asked and launched at a time, and at the end the best trial is written to optimization_results.yaml in the sweep
directory. The seed-averaged objective and the held-out re-run of the best trial are rdsexp's sweep callbacks
(`rdsexp.experiment.sweep`), not the sweeper's.
"""
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import ChoiceSweep, IntervalSweep, Override
from hydra.core.plugins import Plugins
from hydra.plugins.sweeper import Sweeper
from omegaconf import DictConfig, OmegaConf

from rdsexp.errors import ConfigError

log = logging.getLogger(__name__)
SAMPLERS = ("tpe", "random")


@dataclass
class SamplerConf:
    name: str = "tpe"
    seed: int | None = None


@dataclass
class OptunaSweeperConf:
    _target_: str = "hydra_plugins.rdsexp_optuna.optuna_sweeper.OptunaSweeper"
    direction: str = "minimize"
    study_name: str | None = None
    storage: str | None = None
    n_trials: int = 20
    n_jobs: int = 1
    sampler: SamplerConf = field(default_factory=SamplerConf)
    params: dict[str, str] = field(default_factory=dict)


ConfigStore.instance().store(group="hydra/sweeper", name="rdsexp_optuna", node=OptunaSweeperConf,
                             provider="rdsexp")


def distribution(override: Override):
    """The Optuna distribution of a swept override (None: a fixed value)."""
    import optuna
    value = override.value()
    if isinstance(value, ChoiceSweep):
        return optuna.distributions.CategoricalDistribution(list(value.list))
    if isinstance(value, IntervalSweep):
        log_scale = "log" in value.tags
        if isinstance(value.start, int) and isinstance(value.end, int):
            return optuna.distributions.IntDistribution(int(value.start), int(value.end), log=log_scale)
        return optuna.distributions.FloatDistribution(float(value.start), float(value.end), log=log_scale)
    if override.is_sweep_override():
        raise ConfigError(f"hydra.sweeper.params: {override.input_line}: only interval(...), tag(log, interval(...)) "
                         f"and choice(...) are searched")
    return None


class OptunaSweeper(Sweeper):
    def __init__(self, direction: str, study_name: str | None, storage: str | None, n_trials: int, n_jobs: int,
                 sampler: Any, params: Any) -> None:
        try:
            import optuna  # noqa: F401  (before any trial: a missing extra is one line, not a traceback)
        except ImportError:
            raise ConfigError('hydra/sweeper=rdsexp_optuna: Optuna is not installed; pip install -e ".[tune]"') \
                from None
        if direction not in ("minimize", "maximize"):
            raise ConfigError(f"hydra.sweeper.direction: {direction!r} is not allowed, expected minimize or maximize")
        sampler = OmegaConf.to_container(sampler, resolve=True) if OmegaConf.is_config(sampler) else dict(sampler)
        if sampler.get("name", "tpe") not in SAMPLERS:
            raise ConfigError(f"hydra.sweeper.sampler.name: {sampler.get('name')!r} is not allowed, expected one of "
                             f"{', '.join(SAMPLERS)}")
        self.direction, self.study_name, self.storage = direction, study_name, storage
        self.n_trials, self.n_jobs, self.sampler = int(n_trials), max(1, int(n_jobs)), sampler
        self.params = dict(params or {})
        self.config = self.launcher = None
        self.job_idx = 0

    def setup(self, *, hydra_context, task_function, config: DictConfig) -> None:
        self.config = config
        self.launcher = Plugins.instance().instantiate_launcher(hydra_context=hydra_context,
                                                                task_function=task_function, config=config)

    def sweep(self, arguments: list[str]) -> None:
        import optuna
        parser = OverridesParser.create()
        overrides = parser.parse_overrides([f"{k}={v}" for k, v in self.params.items()] + list(arguments))
        space, fixed = {}, []
        for override in overrides:
            found = distribution(override)
            if found is None:
                fixed.append(override.input_line)
                space.pop(override.get_key_element(), None)
            else:
                space[override.get_key_element()] = found
        make = optuna.samplers.TPESampler if self.sampler.get("name", "tpe") == "tpe" else optuna.samplers.RandomSampler
        study = optuna.create_study(study_name=self.study_name, storage=self.storage, direction=self.direction,
                                    sampler=make(seed=self.sampler.get("seed")), load_if_exists=True)
        log.info("Optuna study %s (storage %s), %d trials", study.study_name, self.storage, self.n_trials)
        remaining = self.n_trials
        while remaining > 0:
            trials = [study.ask(space) for _ in range(min(self.n_jobs, remaining))]
            batch = [tuple(fixed + [f"{name}={value}" for name, value in trial.params.items()]) for trial in trials]
            returns = self.launcher.launch(batch, initial_job_idx=self.job_idx)
            self.job_idx += len(returns)
            for trial, ret in zip(trials, returns):
                try:
                    value = float(ret.return_value)
                except (TypeError, ValueError):
                    study.tell(trial, state=optuna.trial.TrialState.FAIL)
                    continue
                if math.isfinite(value):
                    study.tell(trial, value)
                else:                           # a failed run's inf: a failed trial, not a best or worst value
                    study.tell(trial, state=optuna.trial.TrialState.FAIL)
            remaining -= len(trials)
        done = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
        results = {"name": "optuna", "study_name": study.study_name, "trials": len(study.trials)}
        if done:
            results |= {"best_params": dict(study.best_params), "best_value": float(study.best_value)}
        OmegaConf.save(OmegaConf.create(results), Path(self.config.hydra.sweep.dir) / "optimization_results.yaml")
