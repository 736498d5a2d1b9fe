"""rdsexp: EnKF distribution modeling and mean-square stabilization of linear random systems.

`import rdsexp as rx` gives the numerics API (layer 1 of docs/design.md) and `rx.paper`, the paper's
example; the experiment layer (`rdsexp.experiment`) and the report layer (`rdsexp.report`) are
imported on their own, except the run catalog `rx.runs` (search, load, diff). Every name is
imported on first use, so that the command line starts without the numerics' libraries.
"""
import importlib

__version__ = "0.2.0"

# name -> the module that defines it (a submodule itself where the name is a module)
_API = {"AffineRandomSystem": ".numerics.systems", "MomentModel": ".numerics.systems",
        "SynthesisResult": ".numerics.synthesis", "synthesize": ".numerics.synthesis",
        "empirical_rate": ".numerics.analysis", "ms_rate": ".numerics.analysis",
        "second_moments": ".numerics.analysis"}
_MODULES = {"analysis": ".numerics.analysis", "enkf": ".numerics.enkf", "modeling": ".numerics.modeling",
            "simulation": ".numerics.simulation", "synthesis": ".numerics.synthesis", "systems": ".numerics.systems",
            "paper": ".paper", "runs": ".runs"}


def __getattr__(name: str):
    if name in _MODULES:
        value = importlib.import_module(_MODULES[name], __name__)
    elif name in _API:
        value = getattr(importlib.import_module(_API[name], __name__), name)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value               # later accesses skip __getattr__
    return value


def __dir__():
    return sorted([*globals(), *_API, *_MODULES])


__all__ = ["AffineRandomSystem", "MomentModel", "SynthesisResult", "__version__", "analysis", "empirical_rate",
           "enkf", "modeling", "ms_rate", "paper", "second_moments", "simulation", "synthesis", "synthesize",
           "systems"]
