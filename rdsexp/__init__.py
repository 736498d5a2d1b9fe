"""rdsexp: EnKF distribution modeling and mean-square stabilization of linear random systems.

`import rdsexp as rx` gives the numerics API (layer 1 of docs/design.md); the experiment layer
(`rdsexp.experiment`) and the report layer (`rdsexp.report`) are imported on their own, except the
run catalog `rx.runs` (search, load, diff), imported on first use so that the numerics stay light.
"""
from . import paper
from .numerics import (
                       AffineRandomSystem,
                       MomentModel,
                       SynthesisResult,
                       analysis,
                       empirical_rate,
                       enkf,
                       modeling,
                       ms_rate,
                       second_moments,
                       simulation,
                       synthesis,
                       synthesize,
                       systems,
)

__version__ = "0.2.0"


def __getattr__(name: str):
    if name == "runs":                    # rx.runs.search(...), rx.runs.load(...): pandas and Hydra on demand
        import importlib
        return importlib.import_module(".runs", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = ["AffineRandomSystem", "MomentModel", "SynthesisResult", "__version__", "analysis", "empirical_rate",
           "enkf", "modeling", "ms_rate", "paper", "second_moments", "simulation", "synthesis", "synthesize",
           "systems"]
