"""rdsexp: EnKF distribution modeling and mean-square stabilization of linear random systems."""
from . import paper
from .analysis import empirical_rate, ms_rate, second_moments
from .synthesis import SynthesisResult, synthesize
from .systems import AffineRandomSystem, MomentModel

__all__ = ["AffineRandomSystem", "MomentModel", "SynthesisResult", "empirical_rate", "ms_rate", "paper",
           "second_moments", "synthesize"]
